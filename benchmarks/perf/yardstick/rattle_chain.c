/* Speed-of-light yardstick for cost against size: RATTLE on the N-link chain in plain C, O(N).
 *
 * The physics of problems/chain.py at its default parameters: N point masses mass / N at
 * q = (x_1, y_1, ..., x_N, y_N), links of length length / N, the first hinged at the
 * origin, gravity in -y, released from rest with every link at theta0 = pi/4 from the
 * downward vertical (length = mass = 1, gravity = 9.81).
 *
 * One step is the step integrators/rattle.py takes for a separable Hamiltonian:
 *   - position projection: exact Newton on the N multipliers lam of
 *     g(q0 + h/m (p0 + h/2 (F - G(q0)^T lam))) = 0, warm-started from the previous step's
 *     lam, with the Jacobian -h^2/(2m) G(q1) G(q0)^T evaluated at every iterate (as rattle
 *     does by autodiff) and rattle's convergence test (integrators/newton.py: residual at
 *     the tolerance, correction at round-off, residual within twice the round-off floor
 *     after an iteration contracted it by 1e-2, or stalled within 1e3 times the floor).
 *     Constraint k involves points k-1 and k only, so G(q1) G(q0)^T is tridiagonal and
 *     each iteration is one Thomas solve, O(N). The exact Newton is kept rather than a
 *     simplified one (G(q0) G(q0)^T factorised once per step): Thomas fuses factorisation
 *     and solve, so refactorising costs little, and quadratic convergence saves iterations;
 *     it also takes rattle's iteration counts, so the two do the same work per step.
 *   - velocity projection: (h/2m) G(q1) G(q1)^T mu = G(q1) (p_half + h/2 F) / m, one
 *     symmetric tridiagonal Thomas solve.
 *   - bookkeeping: |g|, |G v| (max-norms) and |H - H0| after every step, folded into
 *     per-window maxima (min(N_STEPS, 1000) windows), as the suite's compiled loop does.
 * Thomas without pivoting is safe here: G G^T of the chain is symmetric positive definite
 * (G has full row rank), and G(q1) G(q0)^T differs from it by O(h) per step.
 *
 * usage: rattle_chain N_LINKS N_STEPS H [NEWTON_TOL [state]]  (tolerance default 1e-16,
 *        as rattle's; "state" also prints the final q and v, one line each)
 *     -> "steps seconds cpu_seconds max_g max_gv max_dH newton_iterations peak_kib"
 * (seconds: wall clock of the time loop; cpu_seconds: this process's CPU time in it; set-up
 * and allocation are outside both; peak_kib: the peak resident set since the program
 * started, VmHWM, -1 where /proc does not give it). Exit status 2 on bad arguments, 1 when
 * Newton fails.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "yardstick.h"

#define MAX_WINDOWS 1000
#define MAX_ITER 20

static const double LENGTH = 1.0, MASS = 1.0, GRAVITY = 9.81;
static const double EPS = 2.220446049250313e-16;

/* d[k] = P_k - P_{k-1} (link vectors, P_0 the pivot) for N links, interleaved x, y. */
static void links(long N, const double *q, double *d) {
    d[0] = q[0];
    d[1] = q[1];
    for (long k = 1; k < N; k++) {
        d[2 * k] = q[2 * k] - q[2 * k - 2];
        d[2 * k + 1] = q[2 * k + 1] - q[2 * k - 1];
    }
}

static double dot(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1]; }

/* out = G^T lam for link vectors d: point j gets 2 d_j lam_j - 2 d_{j+1} lam_{j+1}. */
static void g_transpose(long N, const double *d, const double *lam, double *out) {
    for (long j = 0; j < N; j++) {
        double fx = 2.0 * d[2 * j] * lam[j], fy = 2.0 * d[2 * j + 1] * lam[j];
        if (j + 1 < N) {
            fx -= 2.0 * d[2 * j + 2] * lam[j + 1];
            fy -= 2.0 * d[2 * j + 3] * lam[j + 1];
        }
        out[2 * j] = fx;
        out[2 * j + 1] = fy;
    }
}

/* Tridiagonal (A B^T) for the chain's G: rows of link vectors a (left) and b (right),
 * A B^T with sub[k] = (k, k-1), diag[k], sup[k] = (k, k+1), all scaled by s. */
static void chain_product(long N, const double *a, const double *b, double s, double *sub,
                          double *diag, double *sup) {
    for (long k = 0; k < N; k++) {
        diag[k] = s * (k == 0 ? 4.0 : 8.0) * dot(a + 2 * k, b + 2 * k);
        sub[k] = k > 0 ? -4.0 * s * dot(a + 2 * k, b + 2 * k - 2) : 0.0;
        sup[k] = k + 1 < N ? -4.0 * s * dot(a + 2 * k, b + 2 * k + 2) : 0.0;
    }
}

/* Solve the tridiagonal system in place (x holds the right-hand side); w is scratch. */
static void thomas(long N, const double *sub, const double *diag, const double *sup,
                   double *x, double *w) {
    double beta = diag[0];
    x[0] /= beta;
    for (long k = 1; k < N; k++) {
        w[k] = sup[k - 1] / beta;
        beta = diag[k] - sub[k] * w[k];
        x[k] = (x[k] - sub[k] * x[k - 1]) / beta;
    }
    for (long k = N - 2; k >= 0; k--) x[k] -= w[k + 1] * x[k + 1];
}

/* max_k |g_k| for link vectors d. */
static double constraint_norm(long N, const double *d, double l2) {
    double m = 0.0;
    for (long k = 0; k < N; k++) m = fmax(m, fabs(dot(d + 2 * k, d + 2 * k) - l2));
    return m;
}

static double energy(long N, const double *q, const double *p, double mk) {
    double T = 0.0, U = 0.0;
    for (long j = 0; j < N; j++) {
        T += p[2 * j] * p[2 * j] + p[2 * j + 1] * p[2 * j + 1];
        U += q[2 * j + 1];
    }
    return 0.5 * T / mk + mk * GRAVITY * U;
}

int main(int argc, char **argv) {
    long N, n_steps;
    double h, tol;
    int print_state;
    if (parse_arguments(argc, argv, "N_LINKS", &N, &n_steps, &h, &tol, &print_state))
        return 2;
    const double l = LENGTH / N, mk = MASS / N, l2 = l * l;
    const double theta0 = M_PI / 4.0;
    const size_t n = 2 * (size_t)N;
    double *q = malloc(n * sizeof *q), *p = calloc(n, sizeof *p);
    double *q1 = malloc(n * sizeof *q1), *ph = malloc(n * sizeof *ph);
    double *d0 = malloc(n * sizeof *d0), *d1 = malloc(n * sizeof *d1);
    double *f = malloc(n * sizeof *f);
    double *lam = calloc(N, sizeof *lam), *dz = malloc(N * sizeof *dz);
    double *sub = malloc(N * sizeof *sub), *diag = malloc(N * sizeof *diag);
    double *sup = malloc(N * sizeof *sup), *w = malloc(N * sizeof *w);
    const long n_win = n_steps < MAX_WINDOWS ? n_steps : MAX_WINDOWS;
    double(*win)[3] = calloc(n_win, sizeof *win);
    if (!q || !p || !q1 || !ph || !d0 || !d1 || !f || !lam || !dz || !sub || !diag || !sup
        || !w || !win) {
        fprintf(stderr, "out of memory for N = %ld\n", N);
        return 1;
    }
    /* The initial state as problems/chain.py builds it: cumulative sums of the links. */
    double x = 0.0, y = 0.0;
    for (long k = 0; k < N; k++) {
        x += l * sin(theta0);
        y += -(l * cos(theta0));
        q[2 * k] = x;
        q[2 * k + 1] = y;
    }
    const double F[2] = {0.0, -mk * GRAVITY};
    const double H0 = energy(N, q, p, mk);
    const double a = 0.5 * h * h / mk;
    long iterations = 0;
    links(N, q, d0);

    struct timespec t0, t1, c0, c1;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &c0);
    for (long step = 0; step < n_steps; step++) {
        /* Position projection: Newton on lam; q1(lam), p_half(lam) are explicit. */
        g_transpose(N, d0, lam, f);
        for (size_t i = 0; i < n; i++) {
            ph[i] = p[i] + 0.5 * h * (F[i & 1] - f[i]);
            q1[i] = q[i] + h * ph[i] / mk;
        }
        links(N, q1, d1);
        double r = constraint_norm(N, d1, l2), r_prev = INFINITY, dz_norm = INFINITY;
        double terms = 0.0;
        for (long k = 0; k < N; k++) terms = fmax(terms, fabs(lam[k]));
        for (int it = 0;; it++) {
            double lam_norm = 0.0;
            for (long k = 0; k < N; k++) lam_norm = fmax(lam_norm, fabs(lam[k]));
            const double floor_r = fmax(tol, EPS * (1.0 + terms));
            const int stalled = r > 0.5 * r_prev && r <= 1e3 * floor_r;
            const int at_floor = r <= 2.0 * floor_r && r <= 1e-2 * r_prev && isfinite(r_prev);
            if (r <= tol || dz_norm <= 4.0 * EPS * (1.0 + lam_norm) || at_floor || stalled)
                break;
            if (it == MAX_ITER || !isfinite(r)) {
                fprintf(stderr, "Newton did not converge at step %ld (residual %.3e)\n",
                        step + 1, r);
                return 1;
            }
            /* J = -h^2/(2m) G(q1) G(q0)^T at the current iterate. */
            chain_product(N, d1, d0, -a, sub, diag, sup);
            terms = 0.0;
            for (long k = 0; k < N; k++) {
                double t = fabs(diag[k] * lam[k]);
                if (k > 0) t += fabs(sub[k] * lam[k - 1]);
                if (k + 1 < N) t += fabs(sup[k] * lam[k + 1]);
                terms = fmax(terms, t);
                dz[k] = -(dot(d1 + 2 * k, d1 + 2 * k) - l2);
            }
            thomas(N, sub, diag, sup, dz, w);
            dz_norm = 0.0;
            for (long k = 0; k < N; k++) {
                lam[k] += dz[k];
                dz_norm = fmax(dz_norm, fabs(dz[k]));
            }
            iterations++;
            g_transpose(N, d0, lam, f);
            for (size_t i = 0; i < n; i++) {
                ph[i] = p[i] + 0.5 * h * (F[i & 1] - f[i]);
                q1[i] = q[i] + h * ph[i] / mk;
            }
            links(N, q1, d1);
            r_prev = r;
            r = constraint_norm(N, d1, l2);
        }
        /* Velocity projection: (h/2m) G1 G1^T mu = G1 (p_half + h/2 F) / m. */
        for (size_t i = 0; i < n; i++) p[i] = ph[i] + 0.5 * h * F[i & 1];
        chain_product(N, d1, d1, 0.5 * h / mk, sub, diag, sup);
        for (long k = 0; k < N; k++) {
            const double *pk = p + 2 * k;
            const double vx = k > 0 ? pk[0] - pk[-2] : pk[0];
            const double vy = k > 0 ? pk[1] - pk[-1] : pk[1];
            dz[k] = 2.0 * (d1[2 * k] * vx + d1[2 * k + 1] * vy) / mk;
        }
        thomas(N, sub, diag, sup, dz, w);
        g_transpose(N, d1, dz, f);
        for (size_t i = 0; i < n; i++) {
            p[i] -= 0.5 * h * f[i];
            q[i] = q1[i];
        }
        double *swap = d0;
        d0 = d1;
        d1 = swap;
        /* Bookkeeping: |g|, |G v| and |H - H0| at the step's end. */
        double gv = 0.0;
        for (long k = 0; k < N; k++) {
            const double *pk = p + 2 * k;
            const double vx = (k > 0 ? pk[0] - pk[-2] : pk[0]) / mk;
            const double vy = (k > 0 ? pk[1] - pk[-1] : pk[1]) / mk;
            gv = fmax(gv, fabs(2.0 * (d0[2 * k] * vx + d0[2 * k + 1] * vy)));
        }
        const double m[3] = {constraint_norm(N, d0, l2), gv, fabs(energy(N, q, p, mk) - H0)};
        double *row = win[step * n_win / n_steps];
        for (int j = 0; j < 3; j++) row[j] = fmax(row[j], m[j]);
    }
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &c1);
    clock_gettime(CLOCK_MONOTONIC, &t1);
    double mx[3] = {0.0, 0.0, 0.0};
    for (long i = 0; i < n_win; i++)
        for (int j = 0; j < 3; j++) mx[j] = fmax(mx[j], win[i][j]);
    const double secs = (t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec);
    const double cpu = (c1.tv_sec - c0.tv_sec) + 1e-9 * (c1.tv_nsec - c0.tv_nsec);
    printf("%ld %.9f %.9f %.17g %.17g %.17g %ld %ld\n", n_steps, secs, cpu, mx[0], mx[1], mx[2],
           iterations, peak_rss_kib());
    if (print_state) {
        for (size_t i = 0; i < n; i++) printf("%.17g%c", q[i], i + 1 < n ? ' ' : '\n');
        for (size_t i = 0; i < n; i++) printf("%.17g%c", p[i] / mk, i + 1 < n ? ' ' : '\n');
    }
    return 0;
}
