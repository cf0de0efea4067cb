/* Native yardstick of lobatto3ab3: the 3-stage Lobatto IIIA-IIIB (SPARK) step of
 * integrators/lobatto.py on its structured path, in plain C, for pendulum and sps-receiver
 * (two coordinates, one scleronomic constraint, a constant diagonal mass, no other forces).
 *
 * The same unknowns (stage positions Q_j, stage velocities V_j, multipliers Lam_j, the end
 * velocity v1), the same residual blocks, the same start (Q_j = q0 + c_j h v0, V_j = v0,
 * Lam_j = the previous step's last multiplier), the same simplified Newton (the multiplier
 * system S_0 X B^T = R with S_0 = G(q0) M^-1 G(q0)^T scaled to a unit diagonal and
 * factorised once per step, G at the current stage positions where it multiplies a
 * residual) and the same stopping rule as integrators/newton.py (residual at the tolerance,
 * correction at round-off, a residual no longer halving within 8 times its floor
 * eps (1 + terms), stopping where the residual stops halving, the iteration cap), with the
 * tableau's coefficients to the last bit (tests/test_efficiency_spark.py compares them).
 * Where simplified Newton fails, the suite's Newton hands over to Newton with the exact
 * Jacobian; this program fails the step instead: neither problem needs that fallback, and
 * the suite's loop runs without it until a step fails. Per step it also keeps the maxima of |g|,
 * |G v| and |H - H0| over 1000 windows, as the suite's loop does.
 *
 * usage: spark_lobatto3ab3 PROBLEM N_STEPS H NEWTON_TOL MAX_ITER REPEATS q_1 q_2 v_1 v_2
 *     PROBLEM: pendulum (L = 1, mass 1, gravity 9.81) or sps-receiver (M = 0.8, m = 1,
 *     w = 1, bar length from the initial q); the solve runs REPEATS times from the same
 *     start and reports the shortest. Prints lines "steps", "newton" (iterations, all
 *     steps), "seconds" and "cpu_seconds" (wall and CPU time of the loop), "y" (final q, v)
 *     and "max" (|g|, |G v|, |H - H0|). A step whose Newton fails ends the program with
 *     status 1 and the step on stderr; a usage error with status 2.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "common.h"

#define S 3
#define N 2
#define NWIN 1000

enum problem { PENDULUM, SPS_RECEIVER };

static const double EPS = 2.220446049250313e-16;
/* Newton's window of the round-off floor for simplified Newton
 * (integrators.newton.SIMPLIFIED_WINDOW). */
static const double WINDOW = 8.0;
/* A pivot of S_0 at most this times its diagonal is a dependent row (linalg.dense.RANK_RTOL). */
static const double RANK_RTOL = 1e-12;

/* integrators.tableau.lobatto(3) and LobattoIIIAIIIB.tableau()'s B^{-1}, as numpy computes
 * them (zeros are skipped, as integrators.tableau.combine skips them). */
static const double C[S] = {0.0, 0.5, 1.0};
static const double B[S] = {0.16666666666666663, 0.6666666666666667, 0.16666666666666663};
static const double A[S][S] = {{0.0, 0.0, 0.0},
                               {0.20833333333333331, 0.33333333333333337, -0.04166666666666667},
                               {0.16666666666666663, 0.6666666666666667, 0.16666666666666663}};
static const double AH[S][S] = {{0.16666666666666663, -0.16666666666666685, 0.0},
                                {0.16666666666666663, 0.33333333333333337, 0.0},
                                {0.16666666666666663, 0.8333333333333335, 0.0}};
static const double BINV[S][S] = {{16.000000000000004, -2.0000000000000013, 0.0},
                                  {-7.999999999999998, 4.0, 0.0},
                                  {16.000000000000004, -14.000000000000004, 6.000000000000002}};

/* pendulum */
static const double PL = 1.0, PMASS = 1.0, PGRAV = 9.81;
/* sps-receiver */
static const double SM = 0.8, Sm = 1.0, SW = 1.0;

struct system {
    enum problem kind;
    double d[N];   /* the mass diagonal */
    double l2;     /* sps-receiver: the squared bar length */
    double cos6;   /* cos(pi/6) */
};

static inline double constraint(const struct system *P, const double *q) {
    if (P->kind == PENDULUM) return q[0] * q[0] + q[1] * q[1] - PL * PL;
    return q[0] * q[0] + q[1] * q[1] - 2.0 * q[0] * q[1] * P->cos6 - P->l2;
}

/* G(q), the constraint's gradient. */
static inline void gradient(const struct system *P, const double *q, double *G) {
    if (P->kind == PENDULUM) {
        G[0] = 2.0 * q[0];
        G[1] = 2.0 * q[1];
    } else {
        G[0] = 2.0 * q[0] - 2.0 * q[1] * P->cos6;
        G[1] = 2.0 * q[1] - 2.0 * q[0] * P->cos6;
    }
}

static inline double G_times(const struct system *P, const double *q, const double *x) {
    double G[N];
    gradient(P, q, G);
    return G[0] * x[0] + G[1] * x[1];
}

/* grad U(q) */
static inline void grad_potential(const struct system *P, const double *q, double *out) {
    if (P->kind == PENDULUM) {
        out[0] = 0.0;
        out[1] = PMASS * PGRAV;
    } else {
        out[0] = -3.0 * SW * SW * SM * 2.0 * q[0];
        out[1] = -3.0 * SW * SW * Sm * 2.0 * q[1];
    }
}

static inline double energy(const struct system *P, const double *q, const double *v) {
    const double T = 0.5 * (v[0] * P->d[0] * v[0] + v[1] * P->d[1] * v[1]);
    if (P->kind == PENDULUM) return T + PMASS * PGRAV * q[1];
    return T - 3.0 * SW * SW * (SM * q[0] * q[0] + Sm * q[1] * q[1]);
}

/* The unknowns and the residual's blocks (LobattoIIIAIIIB.step). */
struct unknowns { double Q[S][N], V[S][N], Lam[S], v1[N]; };
struct residual { double RQ[S][N], RP[S][N], Rp[N], Rg[S - 1], Rv; };

/* Max-norm over all entries. A NaN is dropped here where jnp.maximum would propagate it:
 * Newton's tests below fail on it alike (isfinite of the residual, of the iterate). */
static inline void end_position(const double *q0, const struct unknowns *z, double h,
                                double *q1) {
    for (int k = 0; k < N; k++)
        q1[k] = q0[k] + h * (B[0] * z->V[0][k] + B[1] * z->V[1][k] + B[2] * z->V[2][k]);
}

static inline void evaluate(const struct system *P, const double *q0, const double *p0,
                            const struct unknowns *z, double h, struct residual *r) {
    double U[S][N], gU[N], q1[N];
    for (int j = 0; j < S; j++) {
        double G[N];
        grad_potential(P, z->Q[j], gU);
        gradient(P, z->Q[j], G);
        for (int k = 0; k < N; k++) U[j][k] = -gU[k] - G[k] * z->Lam[j];
    }
    end_position(q0, z, h, q1);
    for (int j = 0; j < S; j++)
        for (int k = 0; k < N; k++) {
            double a = 0.0, ah = 0.0;
            for (int l = 0; l < S; l++) {
                if (A[j][l] != 0.0) a += A[j][l] * z->V[l][k];
                if (AH[j][l] != 0.0) ah += AH[j][l] * U[l][k];
            }
            r->RQ[j][k] = z->Q[j][k] - q0[k] - h * a;
            r->RP[j][k] = P->d[k] * z->V[j][k] - p0[k] - h * ah;
        }
    for (int k = 0; k < N; k++)
        r->Rp[k] = P->d[k] * z->v1[k] - p0[k] - h * (B[0] * U[0][k] + B[1] * U[1][k]
                                                     + B[2] * U[2][k]);
    for (int i = 1; i < S; i++) r->Rg[i - 1] = constraint(P, z->Q[i]);
    r->Rv = G_times(P, q1, z->v1);
}

static inline double residual_norm(const struct residual *r) {
    return norm_of((const double *)r, (int)(sizeof *r / sizeof(double)));
}

/* S_0 = G M^-1 G^T at q0, as linalg.banded.Banded factorises it for one constraint: the
 * unit-diagonal scaling Dc = 1 / sqrt(S_0) and the reciprocal of the pivot sqrt(Dc^2 S_0). */
struct factor { double Dc, inv; };

static inline struct factor factorise(const struct system *P, const double *q) {
    double G[N];
    gradient(P, q, G);
    const double s = G[0] * G[0] * (1.0 / P->d[0]) + G[1] * G[1] * (1.0 / P->d[1]);
    struct factor F;
    F.Dc = s > 0 ? 1.0 / sqrt(s) : 1.0;
    const double ss = s * F.Dc * F.Dc;
    const double L = ss > RANK_RTOL * ss ? sqrt(ss > 0 ? ss : 1.0) : 0.0;
    F.inv = L != 0.0 ? 1.0 / L : 0.0;
    return F;
}

/* Simplified Newton's correction dz for the residual r at z (LobattoIIIAIIIB.simplified). */
static inline void correction(const struct system *P, const double *q0, double h,
                              struct factor F, const struct unknowns *z,
                              const struct residual *r, struct unknowns *dz) {
    double MinvRP[S][N], q1[N], rhs[S], Y[S], force[S][N], x[N];
    for (int j = 0; j < S; j++)
        for (int k = 0; k < N; k++) MinvRP[j][k] = r->RP[j][k] / P->d[k];
    end_position(q0, z, h, q1);
    const double w2 = 1.0 / (h * h), w1 = 1.0 / h;
    for (int i = 1; i < S; i++) {
        for (int k = 0; k < N; k++)
            x[k] = r->RQ[i][k] + h * (A[i][0] * MinvRP[0][k] + A[i][1] * MinvRP[1][k]
                                      + A[i][2] * MinvRP[2][k]);
        rhs[i - 1] = (r->Rg[i - 1] - G_times(P, z->Q[i], x)) * w2;
    }
    for (int k = 0; k < N; k++) x[k] = r->Rp[k] / P->d[k];
    rhs[S - 1] = (r->Rv - G_times(P, q1, x)) * w1;
    for (int i = 0; i < S; i++) Y[i] = rhs[i] * F.Dc * F.inv * F.inv * F.Dc;
    for (int i = 0; i < S; i++) {
        double acc = 0.0;
        for (int l = 0; l < S; l++)
            if (BINV[i][l] != 0.0) acc += BINV[i][l] * Y[l];
        dz->Lam[i] = acc;
        double G[N];
        gradient(P, z->Q[i], G);
        for (int k = 0; k < N; k++) force[i][k] = G[k] * acc;
    }
    for (int j = 0; j < S; j++)
        for (int k = 0; k < N; k++) {
            double ah = 0.0;
            for (int l = 0; l < S; l++)
                if (AH[j][l] != 0.0) ah += AH[j][l] * force[l][k];
            dz->V[j][k] = (-r->RP[j][k] - h * ah) / P->d[k];
        }
    for (int j = 0; j < S; j++)
        for (int k = 0; k < N; k++) {
            double a = 0.0;
            for (int l = 0; l < S; l++)
                if (A[j][l] != 0.0) a += A[j][l] * dz->V[l][k];
            dz->Q[j][k] = -r->RQ[j][k] + h * a;
        }
    for (int k = 0; k < N; k++)
        dz->v1[k] = (-r->Rp[k] - h * (B[0] * force[0][k] + B[1] * force[1][k]
                                      + B[2] * force[2][k])) / P->d[k];
}

/* One step from (q, p, v, lam) with S_0's factor F (updated to the step's end). Returns the
 * Newton iterations, or -1 where Newton did not converge. */
static inline __attribute__((always_inline)) int step(const struct system *P, double *q, double *p, double *v, double *lam,
                       struct factor *F, double h, double tol, int max_iter) {
    struct unknowns z, dz;
    struct residual r;
    const int nz = (int)(sizeof z / sizeof(double));
    for (int j = 0; j < S; j++) {
        for (int k = 0; k < N; k++) {
            z.Q[j][k] = q[k] + h * C[j] * v[k];
            z.V[j][k] = v[k];
        }
        z.Lam[j] = *lam;
    }
    for (int k = 0; k < N; k++) z.v1[k] = v[k];
    const double p_norm = norm_of(p, N);
    evaluate(P, q, p, &z, h, &r);
    double rn = residual_norm(&r);
    int it = 0, done = rn <= tol;
    int go = !done && it < max_iter && isfinite(rn);
    while (go) {
        const double terms = fmax(norm_of((const double *)&z, nz), p_norm);
        correction(P, q, h, *F, &z, &r, &dz);
        double *zf = (double *)&z;
        const double *df = (const double *)&dz;
        for (int i = 0; i < nz; i++) zf[i] += df[i];
        evaluate(P, q, p, &z, h, &r);
        const double rnew = residual_norm(&r);
        it++;
        const double floor_r = EPS * (1.0 + terms);
        int halved = rnew <= 0.5 * rn;
        halved = halved && !(rnew <= floor_r && rn <= WINDOW * floor_r);
        const int stalled = !halved && rnew <= WINDOW * floor_r;
        done = rnew <= tol || norm_of(df, nz) <= 4 * EPS * (1.0 + norm_of(zf, nz)) || stalled;
        go = !done && it < max_iter && isfinite(rnew) && rnew <= 0.5 * rn;
        rn = rnew;
    }
    for (int i = 0; i < nz; i++)
        if (!isfinite(((const double *)&z)[i])) done = 0;
    if (!done) return -1;
    end_position(q, &z, h, q);
    for (int k = 0; k < N; k++) {
        v[k] = z.v1[k];
        p[k] = P->d[k] * z.v1[k];
    }
    *lam = z.Lam[S - 1];
    *F = factorise(P, q);
    return it;
}

/* The solve from (q0, v0): n steps of h; the final state into q, v, maxima into mx. Returns
 * the Newton iterations, or -(the failing step) where Newton failed. */
static inline __attribute__((always_inline)) long solve(
        const struct system *P, long n, double h, double tol, int max_iter, const double *q0,
        const double *v0, double *q, double *v, double *mx) {
    static double win[NWIN][3];
    double p[N], lam = 0.0;
    long iterations = 0;
    memset(win, 0, sizeof win);
    for (int k = 0; k < N; k++) {
        q[k] = q0[k];
        v[k] = v0[k];
        p[k] = P->d[k] * v0[k];
    }
    const double H0 = energy(P, q0, v0);
    struct factor F = factorise(P, q);
    for (long k = 0; k < n; k++) {
        const int it = step(P, q, p, v, &lam, &F, h, tol, max_iter);
        if (it < 0) return -(k + 1);
        iterations += it;
        const double m[3] = {fabs(constraint(P, q)), fabs(G_times(P, q, v)),
                             fabs(energy(P, q, v) - H0)};
        double *row = win[k * NWIN / n];
        for (int j = 0; j < 3; j++) row[j] = m[j] > row[j] ? m[j] : row[j];
    }
    for (int j = 0; j < 3; j++) mx[j] = 0.0;
    for (int i = 0; i < NWIN; i++)
        for (int j = 0; j < 3; j++) mx[j] = win[i][j] > mx[j] ? win[i][j] : mx[j];
    return iterations;
}

/* The solve compiled once per problem, its branches on the problem and its masses resolved
 * at compile time (as XLA compiles the mass into our loop). */
static long solve_as(enum problem kind, const struct system *P, long n, double h, double tol,
                     int max_iter, const double *q0, const double *v0, double *q, double *v,
                     double *mx) {
    struct system local = *P;   /* the masses are set here */
    if (kind == PENDULUM) {
        local.kind = PENDULUM;
        local.d[0] = local.d[1] = PMASS;
        return solve(&local, n, h, tol, max_iter, q0, v0, q, v, mx);
    }
    local.kind = SPS_RECEIVER;
    local.d[0] = 6.0 * SM;
    local.d[1] = 6.0 * Sm;
    return solve(&local, n, h, tol, max_iter, q0, v0, q, v, mx);
}

int main(int argc, char **argv) {
    struct system P = {.kind = PENDULUM};
    long n, max_iter, repeats;
    double h, tol, q0[N], v0[N];
    int ok = argc == 11 && parse_long(argv[2], &n) && parse_double(argv[3], &h) && h > 0
             && parse_double(argv[4], &tol) && tol > 0 && parse_long(argv[5], &max_iter)
             && parse_long(argv[6], &repeats);
    for (int k = 0; ok && k < N; k++)
        ok = parse_double(argv[7 + k], &q0[k]) && parse_double(argv[9 + k], &v0[k]);
    if (ok && strcmp(argv[1], "pendulum") == 0) {
        P.kind = PENDULUM;
    } else if (ok && strcmp(argv[1], "sps-receiver") == 0) {
        P.kind = SPS_RECEIVER;
    } else {
        fprintf(stderr, "usage: %s pendulum|sps-receiver N_STEPS H NEWTON_TOL MAX_ITER REPEATS "
                        "q_1 q_2 v_1 v_2 (N_STEPS, MAX_ITER, REPEATS whole numbers >= 1; "
                        "H, NEWTON_TOL > 0)\n", argc > 0 ? argv[0] : "spark_lobatto3ab3");
        return 2;
    }
    P.cos6 = cos(M_PI / 6.0);
    P.l2 = q0[0] * q0[0] + q0[1] * q0[1] - 2.0 * q0[0] * q0[1] * P.cos6;
    double q[N] = {0.0, 0.0}, v[N] = {0.0, 0.0}, mx[3] = {0.0, 0.0, 0.0};
    double best = INFINITY, best_cpu = INFINITY;
    long iterations = 0;
    for (long r = 0; r < repeats; r++) {
        const double t0 = seconds_of(CLOCK_MONOTONIC), c0 = seconds_of(CLOCK_PROCESS_CPUTIME_ID);
        iterations = solve_as(P.kind, &P, n, h, tol, (int)max_iter, q0, v0, q, v, mx);
        const double c1 = seconds_of(CLOCK_PROCESS_CPUTIME_ID), t1 = seconds_of(CLOCK_MONOTONIC);
        if (iterations < 0) {
            fprintf(stderr, "%s: Newton did not converge at step %ld\n", argv[1], -iterations);
            return 1;
        }
        best = fmin(best, t1 - t0);
        best_cpu = fmin(best_cpu, c1 - c0);
    }
    printf("steps %ld\nnewton %ld\nseconds %.9f\ncpu_seconds %.9f\n", n, iterations, best,
           best_cpu);
    printf("y %.17g %.17g %.17g %.17g\n", q[0], q[1], v[0], v[1]);
    printf("max %.3e %.3e %.3e\n", mx[0], mx[1], mx[2]);
    return 0;
}
