/* Baumgarte-stabilised explicit Runge-Kutta on the pendulum and the double pendulum: the
 * native cost of `baumgarte-rk4` (fixed step) and `baumgarte-dopri5` (adaptive).
 *
 * The ODE is that of integrators/baumgarte.py, written out by hand for the two problems
 * with their default parameters (problems/pendulum.py, problems/double_pendulum.py):
 * y = (q, v), y' = (v, a) with
 *   S lam = G M^{-1} f + gamma + 2 alpha G v + beta^2 g,   S = G M^{-1} G^T,
 *   a = M^{-1} (f - G^T lam),
 * so that G a + gamma = -2 alpha G v - beta^2 g (the constraints do not depend on time).
 * S is solved as linalg/dense.py's spd_solve does: a 1 x 1 S by a division, a 2 x 2 one
 * scaled to unit diagonal and factorised by Cholesky (a rank-deficient S, which the suite
 * hands to a basic solve, ends this program with an error: it does not occur here).
 *
 * rk4: Kutta's classical method on the grid t_k = t0 + k h, h = T_END / N_STEPS, the last
 * point T_END exactly (integrators/baumgarte.py, FixedSteps).
 * dopri5: Dormand and Prince's 5(4) pair (first stage reused from the last accepted step)
 * under the step control of diffrax's PIDController as the suite sets it: error
 * ||err_i / (atol + rtol max(|y0_i|, |y1_i|))||_RMS, accepted below 1; next step
 * h * clip(safety err^(-1/5), 1 or factormin, factormax or safety) (I-controller,
 * safety 0.9, factormin 0.2, factormax 10); the initial step by the algorithm of Hairer,
 * Norsett and Wanner in diffrax's form; attempts clipped to T_END, and an attempt that
 * would end within 100 ulp of T_END ends there (EmbeddedControl).
 * Stage values are formed as diffrax forms them: y_i = y0 + dt sum_j a_ij f_j, and for rk4
 * y1 = y0 + sum_i b_i (dt f_i), so that rk4 ends where the suite's run ends to round-off.
 *
 * usage: baumgarte_rk pendulum|double-pendulum rk4 ALPHA BETA T_END ROUNDS N_STEPS Q0... V0...
 *        baumgarte_rk pendulum|double-pendulum dopri5 ALPHA BETA T_END ROUNDS RTOL ATOL Q0... V0...
 * (n = 2 or 4 coordinates each; t0 = 0)
 * prints: accepted steps, rejected steps, field evaluations, the best of ROUNDS solve
 * times (s: wall clock, and processor time, which a loaded machine disturbs less), the
 * final y = (q, v).
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define G0 9.81
#define MAXN 8
#define RANK_RTOL 1e-12

static int n;             /* coordinates: 2 or 4 */
static double alpha, beta;
static long evals;

/* Pendulum, L = m = 1: g = x^2 + y^2 - 1. */
static int pendulum(const double *y, double *dy)
{
    const double x = y[0], z = y[1], u = y[2], w = y[3];
    const double g = x * x + z * z - 1.0, Gv = 2.0 * (x * u + z * w);
    const double gamma = 2.0 * (u * u + w * w);
    const double rhs = 2.0 * z * -G0 + gamma + (2.0 * alpha * Gv + beta * beta * g);
    const double lam = rhs / (4.0 * (x * x + z * z));
    dy[0] = u;
    dy[1] = w;
    dy[2] = -2.0 * x * lam;
    dy[3] = -G0 - 2.0 * z * lam;
    return 0;
}

/* Double pendulum, m1 = m2 = L1 = L2 = 1: g = (x1^2 + y1^2 - 1, |p2 - p1|^2 - 1). */
static int double_pendulum(const double *y, double *dy)
{
    const double x1 = y[0], y1 = y[1], x2 = y[2], y2 = y[3];
    const double u1 = y[4], w1 = y[5], u2 = y[6], w2 = y[7];
    const double dx = x2 - x1, dz = y2 - y1, du = u2 - u1, dw = w2 - w1;
    const double g1 = x1 * x1 + y1 * y1 - 1.0, g2 = dx * dx + dz * dz - 1.0;
    const double Gv1 = 2.0 * (x1 * u1 + y1 * w1), Gv2 = 2.0 * (dx * du + dz * dw);
    /* G M^{-1} f: the second row's gravity terms cancel. */
    const double r1 = 2.0 * y1 * -G0 + 2.0 * (u1 * u1 + w1 * w1)
                      + (2.0 * alpha * Gv1 + beta * beta * g1);
    const double r2 = 2.0 * (du * du + dw * dw) + (2.0 * alpha * Gv2 + beta * beta * g2);
    const double S11 = 4.0 * (x1 * x1 + y1 * y1);
    const double S21 = -4.0 * (x1 * dx + y1 * dz);
    const double S22 = 8.0 * (dx * dx + dz * dz);
    /* spd_solve: D S D with unit diagonal, Cholesky, the rank test on the pivots. */
    const double d1 = 1.0 / sqrt(S11), d2 = 1.0 / sqrt(S22);
    const double s21 = S21 * d2 * d1, s22 = S22 * d2 * d2, s11 = S11 * d1 * d1;
    const double L11 = sqrt(s11), L21 = s21 / L11, L22 = sqrt(s22 - L21 * L21);
    const double p1 = L11 * L11, p2 = L22 * L22;
    if (!(fmin(p1, p2) > RANK_RTOL * fmax(p1, p2))) return 1;
    const double z1 = d1 * r1 / L11, z2 = (d2 * r2 - L21 * z1) / L22;
    const double l2 = z2 / L22, l1 = (z1 - L21 * l2) / L11;
    const double lam1 = d1 * l1, lam2 = d2 * l2;
    dy[0] = u1;
    dy[1] = w1;
    dy[2] = u2;
    dy[3] = w2;
    dy[4] = -(2.0 * x1 * lam1 - 2.0 * dx * lam2);
    dy[5] = -G0 - (2.0 * y1 * lam1 - 2.0 * dz * lam2);
    dy[6] = -(2.0 * dx * lam2);
    dy[7] = -G0 - 2.0 * dz * lam2;
    return 0;
}

static int (*field)(const double *y, double *dy);

static void f(const double *y, double *dy)
{
    evals++;
    if (field(y, dy)) {
        fprintf(stderr, "G M^-1 G^T is numerically singular\n");
        exit(1);
    }
}

static double seconds(clockid_t clock)
{
    struct timespec ts;
    clock_gettime(clock, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

/* Kutta's classical RK4, N_STEPS equal steps. */
static long rk4(double *y, double t_end, long n_steps)
{
    static const double b[4] = {1.0 / 6.0, 2.0 / 6.0, 2.0 / 6.0, 1.0 / 6.0};
    const int dim = 2 * n;
    const double h = t_end / (double)n_steps;
    double k[4][2 * MAXN], yi[2 * MAXN];
    for (long s = 0; s < n_steps; s++) {
        const double t0 = s * h, t1 = s + 1 >= n_steps ? t_end : (s + 1) * h;
        const double dt = t1 - t0;
        f(y, k[0]);
        for (int i = 0; i < dim; i++) yi[i] = y[i] + dt * (0.5 * k[0][i]);
        f(yi, k[1]);
        for (int i = 0; i < dim; i++) yi[i] = y[i] + dt * (0.5 * k[1][i]);
        f(yi, k[2]);
        for (int i = 0; i < dim; i++) yi[i] = y[i] + dt * k[2][i];
        f(yi, k[3]);
        for (int i = 0; i < dim; i++)
            y[i] = y[i] + (b[0] * (dt * k[0][i]) + b[1] * (dt * k[1][i])
                           + b[2] * (dt * k[2][i]) + b[3] * (dt * k[3][i]));
    }
    return n_steps;
}

static double rms(const double *x, int dim)
{
    double s = 0.0;
    for (int i = 0; i < dim; i++) s += x[i] * x[i];
    return sqrt(s) / sqrt((double)dim);
}

/* Dormand-Prince 5(4) under diffrax's I-controller; returns accepted steps. */
static long dopri5(double *y, double t_end, double rtol, double atol, long *rejected)
{
    static const double c[7] = {0.0, 1.0 / 5, 3.0 / 10, 4.0 / 5, 8.0 / 9, 1.0, 1.0};
    static const double a[7][6] = {
        {0},
        {1.0 / 5},
        {3.0 / 40, 9.0 / 40},
        {44.0 / 45, -56.0 / 15, 32.0 / 9},
        {19372.0 / 6561, -25360.0 / 2187, 64448.0 / 6561, -212.0 / 729},
        {9017.0 / 3168, -355.0 / 33, 46732.0 / 5247, 49.0 / 176, -5103.0 / 18656},
        {35.0 / 384, 0, 500.0 / 1113, 125.0 / 192, -2187.0 / 6784, 11.0 / 84}};
    static const double e[7] = {35.0 / 384 - 1951.0 / 21600, 0, 500.0 / 1113 - 22642.0 / 50085,
                                125.0 / 192 - 451.0 / 720, -2187.0 / 6784 - -12231.0 / 42400,
                                11.0 / 84 - 649.0 / 6300, -1.0 / 60.0};
    const double safety = 0.9, factormin = 0.2, factormax = 10.0, order = 5.0;
    const int dim = 2 * n;
    double k[7][2 * MAXN], yi[2 * MAXN], err[2 * MAXN], w[2 * MAXN];
    (void)c; /* autonomous fields: stage times are not needed */

    /* Initial step (diffrax's _select_initial_step with the RMS norm). */
    double f0[2 * MAXN], f1[2 * MAXN];
    f(y, f0);
    for (int i = 0; i < dim; i++) w[i] = y[i] / (atol + fabs(y[i]) * rtol);
    const double d0 = rms(w, dim);
    for (int i = 0; i < dim; i++) w[i] = f0[i] / (atol + fabs(y[i]) * rtol);
    const double d1 = rms(w, dim);
    const int tiny = d0 < 1e-5 || d1 < 1e-5;
    const double h0 = tiny ? 1e-6 : 0.01 * (d0 / d1);
    for (int i = 0; i < dim; i++) yi[i] = y[i] + h0 * f0[i];
    f(yi, f1);
    for (int i = 0; i < dim; i++) w[i] = (f1[i] - f0[i]) / (atol + fabs(y[i]) * rtol);
    const double d2 = rms(w, dim) / h0, max_d = fmax(d1, d2);
    const double h1 = max_d <= 1e-15 ? fmax(1e-6, h0 * 1e-3) : pow(0.01 / max_d, 1.0 / order);
    const double floor_t = t_end - 100.0 * (nextafter(t_end, INFINITY) - t_end);
    double t = 0.0, t_next = fmin(t + fmin(100.0 * h0, h1), t_end);

    long accepted = 0;
    *rejected = 0;
    f(y, k[0]);
    while (t < t_end) {
        const double dt = t_next - t;
        for (int s = 1; s < 7; s++) {
            for (int i = 0; i < dim; i++) {
                double sum = 0.0;
                for (int j = 0; j < s; j++) sum += a[s][j] * k[j][i];
                yi[i] = y[i] + dt * sum;
            }
            f(yi, k[s]);
        }
        /* yi is now y1 (the last stage is evaluated at it). */
        int nan1 = 0;
        for (int i = 0; i < dim; i++) nan1 |= isnan(yi[i]);
        for (int i = 0; i < dim; i++) {
            double sum = 0.0;
            for (int s = 0; s < 7; s++) sum += e[s] * (dt * k[s][i]);
            if (isnan(sum)) sum = INFINITY;
            const double scale = fmax(fabs(y[i]), fabs(nan1 ? y[i] : yi[i]));
            err[i] = sum / (atol + scale * rtol);
        }
        const double scaled = rms(err, dim);
        const int keep = scaled < 1.0;
        const double inv = 1.0 / scaled;
        const double fac = fmin(fmax(safety * pow(inv, 1.0 / order), keep ? 1.0 : factormin),
                                keep ? factormax : safety);
        const double t_new = fmin(keep ? t_next : t, t_end);
        double next = (keep ? t_next : t) + dt * fac;
        if (next > floor_t) next = keep ? t_end : t_new + 0.5 * (t_end - t_new);
        if (keep) {
            for (int i = 0; i < dim; i++) {
                if (!isfinite(yi[i])) {
                    fprintf(stderr, "non-finite state at t = %g\n", t_next);
                    exit(1);
                }
                y[i] = yi[i];
                k[0][i] = k[6][i];
            }
            accepted++;
        } else {
            ++*rejected;
        }
        t = t_new;
        t_next = next;
    }
    return accepted;
}

int main(int argc, char **argv)
{
    const int adaptive = argc > 2 && strcmp(argv[2], "dopri5") == 0;
    const int settings = adaptive ? 2 : 1;
    if (argc > 1 && strcmp(argv[1], "pendulum") == 0) {
        n = 2;
        field = pendulum;
    } else if (argc > 1 && strcmp(argv[1], "double-pendulum") == 0) {
        n = 4;
        field = double_pendulum;
    }
    if (!n || argc != 7 + settings + 2 * n || (!adaptive && strcmp(argv[2], "rk4"))) {
        fprintf(stderr, "usage: %s pendulum|double-pendulum rk4 ALPHA BETA T_END ROUNDS "
                        "N_STEPS Q0... V0...\n       %s pendulum|double-pendulum dopri5 "
                        "ALPHA BETA T_END ROUNDS RTOL ATOL Q0... V0...\n", argv[0], argv[0]);
        return 2;
    }
    alpha = atof(argv[3]);
    beta = atof(argv[4]);
    const double t_end = atof(argv[5]);
    const int rounds = atoi(argv[6]);
    const long n_steps = adaptive ? 0 : strtol(argv[7], NULL, 10);
    const double rtol = adaptive ? atof(argv[7]) : 0.0, atol_ = adaptive ? atof(argv[8]) : 0.0;
    double y0[2 * MAXN], y[2 * MAXN];
    for (int i = 0; i < 2 * n; i++) y0[i] = atof(argv[7 + settings + i]);
    if (rounds < 1 || !(t_end > 0) || (!adaptive && n_steps < 1)
        || (adaptive && !(rtol > 0 && atol_ > 0))) {
        fprintf(stderr, "%s: need ROUNDS >= 1, T_END > 0 and N_STEPS >= 1 (rtol, atol > 0)\n",
                argv[0]);
        return 2;
    }
    double best = INFINITY, best_cpu = INFINITY;
    long steps = 0, rejected = 0, calls = 0;
    for (int r = 0; r < rounds; r++) {
        memcpy(y, y0, sizeof y0);
        evals = 0;
        const double start = seconds(CLOCK_MONOTONIC);
        const double start_cpu = seconds(CLOCK_PROCESS_CPUTIME_ID);
        steps = adaptive ? dopri5(y, t_end, rtol, atol_, &rejected) : rk4(y, t_end, n_steps);
        best_cpu = fmin(best_cpu, seconds(CLOCK_PROCESS_CPUTIME_ID) - start_cpu);
        best = fmin(best, seconds(CLOCK_MONOTONIC) - start);
        calls = evals;
    }
    printf("steps %ld\nrejected %ld\nevals %ld\nseconds %.9g\ncpu_seconds %.9g\ny", steps,
           rejected, calls, best, best_cpu);
    for (int i = 0; i < 2 * n; i++) printf(" %.17g", y[i]);
    printf("\n");
    return 0;
}
