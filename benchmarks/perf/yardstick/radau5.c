/* Radau IIA (three stages, order 5) on a mechanical system's index-3 or stabilised index-2
 * form, written out in C step for step as `radau5` and `radau5-ggl` take it: their native
 * cost.
 *
 * The system comes in a header, dae_model.h, that the efficiency benchmark generates from
 * the problem's own JAX functions (linalg/codegen.py): N unknowns y (q, v and the
 * multipliers; the first NQV are q and v), EXPONENT[i] (the index of y_i minus one), the
 * residual R(t, y, y') of integrators/radau.py's formulation and its autodiff blocks
 * J = dR/dy and B = dR/dy' (the singular mass B(y), row-major). The step is the suite's
 * (integrators/radau.py, _attempt) line by line: simplified Newton on the real system
 * gamma/h B + J and the complex one (alpha - i beta)/h B + J, both LU-factorised with
 * power-of-two equilibration and partial pivoting (the complex pivot by |re| + |im| with
 * -DLAPACK_PIVOT, as LAPACK's zgetrf takes it for systems above the suite's INLINE_MAX, by
 * the modulus otherwise); starting values extrapolated from the last collocation
 * polynomial; RADAU5's test on the scaled increments, up to two more iterations, the
 * constraint rows at the step end to round-off; Hairer's embedded estimate with the index
 * scaling h^(k-1) and B at the step's start; the step-size controller with Gustafsson's
 * predictive part; Jacobian reuse while Newton's contraction is at most thet,
 * factorisations kept for step ratios in [1, 1.2]; a Newton failure with a kept Jacobian
 * retried at the same step with a fresh one.
 *
 * The eigenbasis T of A^-1 is a choice of normalisation that the Newton norms depend on,
 * so the tableau comes on the command line from integrators.radau.radau_iia, as do the
 * initial values (the suite's consistent_values): both runs start from the same point
 * with the same coefficients.
 *
 * usage: radau5 RTOL ATOL MULTIPLIER_ATOL THET NEWTON_TOL NIT SAFETY FIRST_STEP MAX_STEP
 *        T0 T_END ROUNDS Y0(N) YP0(N) C(3) A_INV(9) T(9) T_INV(9) GAMMA ALPHA BETA E(3)
 * (matrices row by row)
 * prints: steps, rejected, jacobians, lu (pairs of factorisations), newton iterations,
 * residual evaluations, linear solves, the best of ROUNDS solve times (wall and processor,
 * s), final y.
 */
#include <complex.h>
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "common.h"

#include "dae_model.h"

#define EPS DBL_EPSILON
/* The constants of integrators/radau.py and linalg/dense.py. */
#define RANK_RTOL 1e-12
#define KEEP_LO 1.0
#define KEEP_HI 1.2
#define FACTOR_MIN 0.2
#define FACTOR_MAX 8.0
#define NEWTON_TIGHT 1e-2
#define NEWTON_EXTRA 2
#define UNDERFLOW_ULPS 16

typedef double complex cplx;

static double C[3], AI[3][3], T[3][3], TI[3][3], GAMMA, ALPHA, BETA, E[3];
static double RTOL, ATOL, MATOL, THET, NEWTON_TOL, SAFETY, FIRST_STEP, MAX_STEP, FNEWT;
static int NIT;

/* 2^-round(log2 x) for x > 0 (1 for 0), as linalg.dense.power_of_two_scale. */
static double p2scale(double x)
{
    if (!(x > 0)) return 1.0;
    int e;
    const double f = frexp(x, &e);
    int k = (f < sqrt(0.5)) - e;
    if (k < -1022) k = -1022;
    if (k > 1023) k = 1023;
    return ldexp(1.0, k);
}

/* LU with power-of-two equilibration and partial pivoting (first largest modulus), as
 * integrators.radau.inline_lu_factor; piv is the row permutation. Written once for the
 * real system (TYPE double) and once for the complex one. */
#define DEFINE_LU(LU_T, FACTOR, SOLVE, TYPE, ABS, PABS)                                        \
    typedef struct {                                                                       \
        TYPE lu[N][N];                                                                     \
        double row[N], col[N];                                                             \
        int piv[N];                                                                        \
    } LU_T;                                                                                \
                                                                                           \
    static int FACTOR(LU_T *F, TYPE A[N][N])                                               \
    {                                                                                      \
        for (int i = 0; i < N; i++) {                                                      \
            double m = 0.0;                                                                \
            for (int j = 0; j < N; j++) m = fmax(m, ABS(A[i][j]));                         \
            F->row[i] = p2scale(m);                                                        \
        }                                                                                  \
        for (int j = 0; j < N; j++) {                                                      \
            double m = 0.0;                                                                \
            for (int i = 0; i < N; i++) m = fmax(m, ABS(A[i][j] * F->row[i]));             \
            F->col[j] = p2scale(m);                                                        \
        }                                                                                  \
        for (int i = 0; i < N; i++) {                                                      \
            F->piv[i] = i;                                                                 \
            for (int j = 0; j < N; j++) F->lu[i][j] = A[i][j] * F->row[i] * F->col[j];     \
        }                                                                                  \
        for (int k = 0; k < N; k++) {                                                      \
            int p = k;                                                                     \
            double best = PABS(F->lu[k][k]);                                               \
            for (int i = k + 1; i < N; i++)                                                \
                if (PABS(F->lu[i][k]) > best) best = PABS(F->lu[p = i][k]);                \
            if (p != k) {                                                                  \
                TYPE tmp[N];                                                               \
                memcpy(tmp, F->lu[k], sizeof tmp);                                         \
                memcpy(F->lu[k], F->lu[p], sizeof tmp);                                    \
                memcpy(F->lu[p], tmp, sizeof tmp);                                         \
                const int t = F->piv[k];                                                   \
                F->piv[k] = F->piv[p];                                                     \
                F->piv[p] = t;                                                             \
            }                                                                              \
            for (int i = k + 1; i < N; i++) {                                              \
                const TYPE l = F->lu[i][k] / F->lu[k][k];                                  \
                F->lu[i][k] = l;                                                           \
                for (int j = k + 1; j < N; j++) F->lu[i][j] -= l * F->lu[k][j];            \
            }                                                                              \
        }                                                                                  \
        double lo = INFINITY, hi = 0.0;                                                    \
        for (int i = 0; i < N; i++) {                                                      \
            lo = fmin(lo, ABS(F->lu[i][i]));                                               \
            hi = fmax(hi, ABS(F->lu[i][i]));                                               \
        }                                                                                  \
        return lo > RANK_RTOL * hi;                                                        \
    }                                                                                      \
                                                                                           \
    static void SOLVE(const LU_T *F, const TYPE *b, TYPE *x)                               \
    {                                                                                      \
        for (int i = 0; i < N; i++) x[i] = b[F->piv[i]] * F->row[F->piv[i]];              \
        for (int i = 1; i < N; i++)                                                        \
            for (int j = 0; j < i; j++) x[i] -= F->lu[i][j] * x[j];                        \
        for (int i = N - 1; i >= 0; i--) {                                                 \
            for (int j = i + 1; j < N; j++) x[i] -= F->lu[i][j] * x[j];                    \
            x[i] /= F->lu[i][i];                                                           \
        }                                                                                  \
        for (int i = 0; i < N; i++) x[i] *= F->col[i];                                     \
    }

#ifdef LAPACK_PIVOT
static double cabs1(cplx x) { return fabs(creal(x)) + fabs(cimag(x)); }
#define PIVOT_ABS cabs1
#else
#define PIVOT_ABS cabs
#endif
DEFINE_LU(LU, lu_factor, solve_real, double, fabs, fabs)
DEFINE_LU(LUc, lu_factor_complex, solve_complex, cplx, cabs, PIVOT_ABS)

typedef struct {
    LU real;
    LUc pair;
} Factors;

/* LU of gamma/h B + J and of (alpha - i beta)/h B + J. */
static int factor(double J[N][N], double B[N][N], double h, Factors *F)
{
    double A1[N][N];
    cplx A2[N][N];
    const double s1 = GAMMA / h;
    const cplx s2 = (ALPHA - I * BETA) / h;
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++) {
            A1[i][j] = s1 * B[i][j] + J[i][j];
            A2[i][j] = s2 * B[i][j] + J[i][j];
        }
    return lu_factor(&F->real, A1) && lu_factor_complex(&F->pair, A2);
}

static double rms(const double *x, const double *scal, int n)
{
    double s = 0.0;
    for (int i = 0; i < n; i++) s += (x[i] / scal[i % N]) * (x[i] / scal[i % N]);
    return sqrt(s / n);
}

static double clip(double x, double lo, double hi) { return fmin(fmax(x, lo), hi); }

typedef struct {
    /* J, B: the frozen iteration blocks; Bn: B at (t, y), for the error estimate. */
    double t, h, y[N], w[N], f0[N], J[N][N], B[N][N], Bn[N][N], h_lu, Z[3][N], h_z, faccon;
    double h_acc, err_acc;
    Factors F;
    int fresh, need_jac, first, reject;
    long accepted, rejected, f_evals, jac_evals, newton, lin_solves, lu;
} State;

static int init(State *s, double t0, double t_end, const double *y0, const double *yp0)
{
    static const double zero[N];
    memset(s, 0, sizeof *s);
    s->t = t0;
    memcpy(s->y, y0, sizeof s->y);
    memcpy(s->w, yp0, sizeof s->w);
    jacobian(t0, s->y, s->w, &s->J[0][0]);
    mass(t0, s->y, s->w, &s->B[0][0]);
    mass(t0, s->y, zero, &s->Bn[0][0]);
    s->h = fmin(fmin(FIRST_STEP, MAX_STEP), t_end - t0);
    if (!factor(s->J, s->B, s->h, &s->F)) return 0;
    residual(t0, s->y, zero, s->f0);
    for (int i = 0; i < N; i++) s->f0[i] = -s->f0[i];
    s->h_lu = s->h_z = s->h_acc = s->h;
    s->faccon = 1.0;
    s->err_acc = 1e-2;
    s->fresh = s->first = 1;
    s->f_evals = s->jac_evals = s->lu = 1;
    return 1;
}

/* One step attempt; returns 0, or -1 (rank-deficient stage matrix), -2 (step underflow). */
static int attempt(State *s, double t_end)
{
    static const double zero[N];
    const double t = s->t;
    const int last = t + 1.0001 * s->h >= t_end;
    const double h = last ? t_end - t : s->h;
    const double t1 = last ? t_end : t + h;
    if (s->need_jac) {
        jacobian(t, s->y, s->w, &s->J[0][0]);
        mass(t, s->y, s->w, &s->B[0][0]);
    }
    const int refactor = s->need_jac || h != s->h_lu;
    if (refactor && !factor(s->J, s->B, h, &s->F)) return -1;
    const int fresh = s->fresh || s->need_jac;
    double h_index[N], scal[N], floor_[N];
    for (int i = 0; i < N; i++) {
        h_index[i] = pow(h, EXPONENT[i]);
        scal[i] = ((i < NQV ? ATOL : MATOL) + RTOL * fabs(s->y[i])) / h_index[i];
    }
    double Z[3][N];
    if (s->first) {
        memset(Z, 0, sizeof Z);
    } else {
        /* The last step's collocation polynomial P (P(0) = 0, P(c_k) = Z_k) at 1 + c_i r,
         * less P(1). */
        const double r = h / s->h_z, x[4] = {0.0, C[0], C[1], C[2]};
        for (int i = 0; i < 3; i++) {
            const double th = 1.0 + C[i] * r;
            double L[3];
            for (int k = 1; k < 4; k++) {
                L[k - 1] = 1.0;
                for (int j = 0; j < 4; j++)
                    if (j != k) L[k - 1] *= (th - x[j]) / (x[k] - x[j]);
            }
            for (int n = 0; n < N; n++)
                Z[i][n] = L[0] * s->Z[0][n] + L[1] * s->Z[1][n] + L[2] * s->Z[2][n]
                          - s->Z[2][n];
        }
    }
    /* Round-off floors: eps (1 + |J||y| + |B||y'|) row by row, J and B the kept blocks. */
    for (int i = 0; i < N; i++) {
        double a = 0.0, b = 0.0;
        for (int j = 0; j < N; j++) {
            a += fabs(s->J[i][j]) * fabs(s->y[j]);
            b += fabs(s->B[i][j]) * fabs(s->w[j]);
        }
        floor_[i] = EPS * (1.0 + a + b);
    }
    double faccon = pow(fmax(s->faccon, EPS), 0.8);
    int k = 0, k_ok = 0, held = 0, status = 0;
    double dynold = 1.0, thqold = 1.0, theta = 0.0, theta_ok = 0.0, cres = INFINITY;
    double res_prev = INFINITY, hhfac = 1.0;
    while (status == 0) {
        double Rs[3][N], res = 0.0;
        for (int i = 0; i < 3; i++) {
            double Y[N], K[N];
            for (int n = 0; n < N; n++) {
                Y[n] = s->y[n] + Z[i][n];
                K[n] = (AI[i][0] * Z[0][n] + AI[i][1] * Z[1][n] + AI[i][2] * Z[2][n]) / h;
            }
            residual(t + C[i] * h, Y, K, Rs[i]);
            for (int n = 0; n < N; n++) res = fmax(res, fabs(Rs[i][n]) / floor_[n]);
        }
        const int at_floor = res <= 1e3;
        const int noise = k >= 1 && at_floor && res > 0.5 * res_prev && held;
        double rho[3][N], dW[3][N];
        for (int i = 0; i < 3; i++)
            for (int n = 0; n < N; n++)
                rho[i][n] = -(TI[i][0] * Rs[0][n] + TI[i][1] * Rs[1][n] + TI[i][2] * Rs[2][n]);
        cplx b[N], d12[N];
        for (int n = 0; n < N; n++) b[n] = rho[1][n] + I * rho[2][n];
        solve_complex(&s->F.pair, b, d12);
        solve_real(&s->F.real, rho[0], dW[0]);
        int finite = 1;
        for (int n = 0; n < N; n++) {
            dW[1][n] = creal(d12[n]);
            dW[2][n] = cimag(d12[n]);
            finite &= isfinite(dW[0][n]) && isfinite(dW[1][n]) && isfinite(dW[2][n]);
        }
        const double dyno = rms(&dW[0][0], scal, 3 * N);
        k++;
        const double thq = dyno / dynold;
        theta = k == 1 ? theta : (k == 2 ? thq : sqrt(thq * thqold));
        const int contracting = theta < 0.99;
        if (k > 1 && contracting) faccon = theta / (1.0 - theta);
        const double dyth = faccon * dyno * pow(theta, NIT - 1 - k) / FNEWT;
        const int diverged = !finite || (k > 1 && !contracting && !at_floor && k_ok == 0);
        const int slow = k > 1 && k < NIT && k_ok == 0 && dyth >= 1.0 && !at_floor;
        hhfac = 0.8 * pow(clip(dyth, 1e-4, 20.0), -1.0 / (double)(4 + NIT - 1 - k));
        double Z1[3][N];
        for (int i = 0; i < 3; i++)
            for (int n = 0; n < N; n++)
                Z1[i][n] = Z[i][n] + (T[i][0] * dW[0][n] + T[i][1] * dW[1][n]
                                      + T[i][2] * dW[2][n]);
        const int passed = k_ok == 0 && faccon * dyno <= FNEWT;
        if (passed) {
            theta_ok = theta;
            k_ok = k;
        }
        const int tight = faccon * dyno <= NEWTON_TIGHT * FNEWT;
        const int done = k_ok > 0 && (tight || at_floor || !contracting
                                      || k - k_ok >= NEWTON_EXTRA);
        /* The constraint rows at the step end (t1 does not enter them). */
        double Y1[N], r1[N], con = 0.0, cres1 = 0.0;
        for (int n = 0; n < N; n++) Y1[n] = s->y[n] + Z1[2][n];
        residual(t1, Y1, zero, r1);
        for (int n = NQV; n < N; n++) {
            con = fmax(con, fabs(r1[n]));
            cres1 = fmax(cres1, fabs(r1[n]) / floor_[n]);
        }
        const int held1 = con <= NEWTON_TOL || (cres1 > 0.5 * cres && cres1 <= 1e2);
        const int spent = k_ok == 0 ? k >= NIT : k - k_ok >= NIT;
        status = noise ? 1 : diverged ? 2 : slow ? 3 : (done && held1) ? 1 : spent ? 2 : 0;
        if (!noise) memcpy(Z, Z1, sizeof Z);
        dynold = fmax(dyno, EPS);
        thqold = thq;
        cres = cres1;
        held = held1;
        res_prev = res;
    }
    double y1[N];
    int converged = status == 1;
    for (int n = 0; n < N; n++) {
        y1[n] = s->y[n] + Z[2][n];
        converged &= isfinite(y1[n]);
    }
    double en = INFINITY;
    int again = 0;
    if (converged) {
        /* The embedded error, filtered through the real iteration matrix. */
        const double gamma0 = 1.0 / GAMMA;
        double ez[N], Bez[N], scal_e[N], rhs[N], err[N];
        for (int n = 0; n < N; n++)
            ez[n] = ((E[0] / gamma0) * Z[0][n] + (E[1] / gamma0) * Z[1][n]
                     + (E[2] / gamma0) * Z[2][n]) / h;
        for (int n = 0; n < N; n++) {
            Bez[n] = 0.0;
            for (int j = 0; j < N; j++) Bez[n] += s->Bn[n][j] * ez[j];
            scal_e[n] = ((n < NQV ? ATOL : MATOL) + RTOL * fmax(fabs(s->y[n]), fabs(y1[n])))
                        / h_index[n];
            rhs[n] = s->f0[n] + Bez[n];
        }
        solve_real(&s->F.real, rhs, err);
        again = rms(err, scal_e, N) >= 1.0 && (s->first || s->reject);
        if (again) {
            double ye[N], r[N];
            for (int n = 0; n < N; n++) ye[n] = s->y[n] + err[n];
            residual(t, ye, zero, r);
            for (int n = 0; n < N; n++) rhs[n] = -r[n] + Bez[n];
            solve_real(&s->F.real, rhs, err);
        }
        en = fmax(rms(err, scal_e, N), 1e-10);
    }
    const int accept = converged && en < 1.0;
    const double fac = fmin(SAFETY, SAFETY * (1 + 2 * NIT) / (k_ok + 2 * NIT));
    double quot = clip(pow(en, 0.25) / fac, 1.0 / FACTOR_MAX, 1.0 / FACTOR_MIN);
    const double gus = clip((s->h_acc / h) * pow(en * en / s->err_acc, 0.25) / SAFETY,
                            1.0 / FACTOR_MAX, 1.0 / FACTOR_MIN);
    if (accept && s->accepted >= 1) quot = fmax(quot, gus);
    const double h_new = fmin(h / quot, MAX_STEP);
    const int new_jac = theta_ok > THET;
    const double ratio = h_new / h;
    double h_acc_next = s->reject ? fmin(h_new, h) : h_new;
    if (!new_jac && ratio >= KEEP_LO && ratio <= KEEP_HI) h_acc_next = h;
    const int stale = !converged && !fresh;
    const double h_next = accept ? h_acc_next
                          : stale ? h
                          : status == 2 ? 0.5 * h
                          : status == 3 ? hhfac * h
                          : s->first ? 0.1 * h : h_new;
    s->rejected += !accept;
    s->f_evals += 3 * k + accept + again;
    s->jac_evals += s->need_jac;
    s->newton += k;
    s->lin_solves += 2 * k + converged + again;
    s->lu += refactor;
    s->need_jac = accept ? new_jac : (converged ? 0 : !fresh);
    s->h_lu = h;
    s->h = h_next;
    s->faccon = faccon;
    s->fresh = fresh && !accept;
    if (accept) {
        s->t = t1;
        memcpy(s->y, y1, sizeof y1);
        for (int n = 0; n < N; n++)
            s->w[n] = (AI[2][0] * Z[0][n] + AI[2][1] * Z[1][n] + AI[2][2] * Z[2][n]) / h;
        residual(t1, s->y, zero, s->f0);
        for (int n = 0; n < N; n++) s->f0[n] = -s->f0[n];
        mass(t1, s->y, zero, &s->Bn[0][0]);
        memcpy(s->Z, Z, sizeof Z);
        s->h_z = h;
        s->h_acc = h;
        s->err_acc = fmax(1e-2, en);
        s->accepted++;
        s->first = 0;
    }
    s->reject = !accept;
    if (!accept && h_next <= UNDERFLOW_ULPS * EPS * fmax(1.0, fabs(t))) return -2;
    return 0;
}

#define N_ARGS (12 + 2 * N + 3 + 27 + 3 + 3)

int main(int argc, char **argv)
{
    if (argc != 1 + N_ARGS) {
        fprintf(stderr, "usage: %s RTOL ATOL MULTIPLIER_ATOL THET NEWTON_TOL NIT SAFETY "
                        "FIRST_STEP MAX_STEP T0 T_END ROUNDS Y0(%d) YP0(%d) C(3) A_INV(9) T(9) "
                        "T_INV(9) GAMMA ALPHA BETA E(3)\n", argv[0], N, N);
        return 2;
    }
    double v[N_ARGS];
    if (parse_numbers(argv, N_ARGS, v)) return 2;
    RTOL = v[0], ATOL = v[1], MATOL = v[2], THET = v[3], NEWTON_TOL = v[4];
    NIT = (int)v[5], SAFETY = v[6], FIRST_STEP = v[7], MAX_STEP = v[8];
    const double t0 = v[9], t_end = v[10];
    const int rounds = (int)v[11];
    const double *y0 = v + 12, *yp0 = v + 12 + N, *tab = v + 12 + 2 * N;
    memcpy(C, tab, sizeof C);
    memcpy(AI, tab + 3, sizeof AI);
    memcpy(T, tab + 12, sizeof T);
    memcpy(TI, tab + 21, sizeof TI);
    GAMMA = tab[30], ALPHA = tab[31], BETA = tab[32];
    memcpy(E, tab + 33, sizeof E);
    /* RADAU5's tolerance of Newton's test, max(10 eps/rtol, min(0.03, rtol^(1/2))). */
    FNEWT = fmax(10 * EPS / RTOL, fmin(0.03, sqrt(RTOL)));
    if (!(RTOL > 0 && ATOL > 0 && MATOL > 0 && NIT >= 1 && rounds >= 1 && t_end > t0)) {
        fprintf(stderr, "%s: need RTOL, ATOL, MULTIPLIER_ATOL > 0, T_END > T0 and NIT, "
                        "ROUNDS >= 1\n", argv[0]);
        return 2;
    }
    double best = INFINITY, best_cpu = INFINITY;
    State s;
    for (int r = 0; r < rounds; r++) {
        const double start = seconds_of(CLOCK_MONOTONIC);
        const double cpu = seconds_of(CLOCK_PROCESS_CPUTIME_ID);
        if (!init(&s, t0, t_end, y0, yp0)) {
            fprintf(stderr, "rank-deficient stage matrix at t = %.17g\n", t0);
            return 1;
        }
        while (s.t < t_end) {
            const int code = attempt(&s, t_end);
            if (code) {
                fprintf(stderr, "%s at t = %.17g\n", code == -1 ? "rank-deficient stage matrix"
                                                                : "step size underflow", s.t);
                return 1;
            }
        }
        best = fmin(best, seconds_of(CLOCK_MONOTONIC) - start);
        best_cpu = fmin(best_cpu, seconds_of(CLOCK_PROCESS_CPUTIME_ID) - cpu);
    }
    printf("steps %ld\nrejected %ld\njacobians %ld\nlu %ld\nnewton %ld\nf_evals %ld\n"
           "lin_solves %ld\nseconds %.9g\ncpu_seconds %.9g\ny", s.accepted, s.rejected,
           s.jac_evals, s.lu, s.newton, s.f_evals, s.lin_solves, best, best_cpu);
    for (int i = 0; i < N; i++) printf(" %.17g", s.y[i]);
    printf("\n");
    return 0;
}
