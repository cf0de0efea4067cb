/* Native yardstick of rattle, genalpha and lobatto3ab3 on andrews: each method's step on
 * the suite's structured path, in plain C, for a configuration-dependent (non-diagonal)
 * mass M(q).
 *
 * The model comes from andrews_model.h, which benchmarks/perf/efficiency.py writes at run
 * time from the problem's own autodiff-derived functions (linalg/codegen.py), so that the
 * physics and the coefficients have one source: N and M (the numbers of coordinates and
 * constraints), mass_matrix(q) = M(q), hamilton_force(q, v) = -H_q at v = M^-1 p (the
 * spring force and dT/dq), lagrange_force(q, v) = -grad U + dT/dq - (dM/dq v) v,
 * constraint_jacobian(q) = G, configuration(q) = (M, g, G) at once (their shared sines
 * and cosines computed once), curvature(q, v) (G a + curvature = 0), energy(q, v); the
 * Jacobians that the exact Newton's products are made of: mass_dq(q, x) = d(M(q) x)/dq,
 * hamilton_force_d and lagrange_force_d(q, v) = [d/dq, d/dv] (N x 2N), gt_dq(q, lam) =
 * d(G^T lam)/dq, gv_dq(q, v) = d(G v)/dq (all in C order); and lobatto3ab3's stage count
 * S and tableau (A, AH, B, C, BINV: LobattoIIIAIIIB.tableau()).
 *
 * Per method the same unknowns, residual blocks, start, warm start and simplified Newton as
 * integrators/rattle.py (the general position projection: unknowns p_1/2, q1, lambda),
 * integrators/genalpha.py (index-3 form: x = beta h^2 a_n+1, Lambda = beta h^2 lambda)
 * and integrators/lobatto.py (stage positions, stage velocities, multipliers, v1): the
 * iteration matrix frozen at the step's start through S_0 = G(q0) M(q0)^-1 G(q0)^T,
 * factorised once per step (rattle and lobatto3ab3 carry the factor of the previous step's
 * end; genalpha factorises at q_n and mixes its corrections by Anderson's method of depth
 * one, as it asks integrators/newton.py to), and newton.py's stopping rule for simplified
 * Newton (residual at the tolerance, correction at round-off, a residual no longer halving
 * within 8 times its floor eps (1 + terms), stopping where the residual stops halving,
 * the iteration cap). The linear algebra is that of the structured path written out small
 * and dense: a Cholesky factor of M(q) (7 x 7, its zero blocks stay zero), S_0 whitened by
 * it, scaled to a unit diagonal and factorised by Cholesky with the suite's pivot rule for
 * dependent rows (linalg.banded.pivot). Where simplified Newton does not converge, Newton
 * with the exact Jacobian takes over as in the suite: its corrections by BiCGSTAB on the
 * products J(z) x (linalg/krylov.py), preconditioned by the simplified correction, from the
 * better of the first guess and the last iterate; the derivatives those products are made
 * of are formed once per iterate, as the suite linearises the residual once per
 * correction. G at a configuration is formed once and reused by the residual, the
 * correction and the products at the same iterate, where the suite takes products with it
 * by autodiff. Per step the loop keeps the maxima of |g|, |G v| and |H - H0| over 1000
 * windows, as the suite's loop does.
 *
 * usage: dense_andrews METHOD N_STEPS H NEWTON_TOL MAX_ITER REPEATS AM AF GAMMA BETA
 *                      q_1..q_N v_1..v_N
 *     METHOD: rattle, genalpha or lobatto3ab3; AM AF GAMMA BETA: genalpha's alpha_m,
 *     alpha_f, gamma, beta (read, and unused by the others). The solve runs REPEATS times
 *     from the same start and reports the shortest. Prints lines "steps", "newton"
 *     (iterations, all steps), "exact_steps" (steps on which Newton with the exact Jacobian
 *     took over), "krylov" (its BiCGSTAB iterations), "seconds" and "cpu_seconds" (wall
 *     and CPU time of the loop), "y" (final q, v) and "max" (|g|, |G v|, |H - H0|). A step
 *     whose Newton fails ends the program with status 1 and the step on stderr; a usage
 *     error with status 2.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "common.h"

#include "andrews_model.h"

#define NWIN 1000

enum method { RATTLE, GENALPHA, LOBATTO };

static const double EPS = 2.220446049250313e-16;
/* integrators.newton.SIMPLIFIED_WINDOW */
static const double WINDOW = 8.0;
/* linalg.dense.RANK_RTOL */
static const double RANK_RTOL = 1e-12;

/* --- small dense linear algebra ---------------------------------------------------- */

/* The lower Cholesky factor of the mass matrix (M = L L^T). */
struct mass { double L[N][N]; };

/* M(q), g(q) and G(q) at one configuration, from one generated function (configuration)
 * that computes the sines and cosines they share once. */
struct config { double mass[N * N], g[M], G[M * N]; };

static inline void cholesky(const double *Mq, struct mass *F) {
    for (int j = 0; j < N; j++) {
        double d = Mq[j * N + j];
        for (int k = 0; k < j; k++) d -= F->L[j][k] * F->L[j][k];
        F->L[j][j] = sqrt(d);
        for (int i = j + 1; i < N; i++) {
            double a = Mq[i * N + j];
            for (int k = 0; k < j; k++) a -= F->L[i][k] * F->L[j][k];
            F->L[i][j] = a / F->L[j][j];
        }
        for (int i = 0; i < j; i++) F->L[i][j] = 0.0;
    }
}

static inline void mass_factor(const double *q, struct mass *F) {
    double Mq[N * N];
    mass_matrix(q, Mq);
    cholesky(Mq, F);
}

static inline void forward(const struct mass *F, const double *b, double *y) {
    for (int i = 0; i < N; i++) {
        double a = b[i];
        for (int k = 0; k < i; k++) a -= F->L[i][k] * y[k];
        y[i] = a / F->L[i][i];
    }
}

/* x = M^-1 b (x may be b). */
static inline void mass_solve(const struct mass *F, const double *b, double *x) {
    double y[N];
    forward(F, b, y);
    for (int i = N - 1; i >= 0; i--) {
        double a = y[i];
        for (int k = i + 1; k < N; k++) a -= F->L[k][i] * x[k];
        x[i] = a / F->L[i][i];
    }
}

static inline void mass_times(const double *q, const double *x, double *out) {
    double Mq[N * N];
    mass_matrix(q, Mq);
    for (int i = 0; i < N; i++) {
        double a = 0.0;
        for (int k = 0; k < N; k++) a += Mq[i * N + k] * x[k];
        out[i] = a;
    }
}

/* G x and G^T y for G (M x N, C order). */
static inline void G_times(const double *G, const double *x, double *out) {
    for (int i = 0; i < M; i++) {
        double a = 0.0;
        for (int k = 0; k < N; k++) a += G[i * N + k] * x[k];
        out[i] = a;
    }
}

static inline void GT_times(const double *G, const double *y, double *out) {
    for (int k = 0; k < N; k++) {
        double a = 0.0;
        for (int i = 0; i < M; i++) a += G[i * N + k] * y[i];
        out[k] = a;
    }
}

/* out = A x (+ out where add) for A (rows x cols, row stride ld). */
static inline void matvec(const double *A, int rows, int cols, int ld, const double *x,
                          double *out, int add) {
    for (int i = 0; i < rows; i++) {
        double a = 0.0;
        for (int k = 0; k < cols; k++) a += A[i * ld + k] * x[k];
        out[i] = add ? out[i] + a : a;
    }
}

/* S = G M^-1 G^T = W W^T with W = G L^-T, scaled to a unit diagonal (Dc S Dc) and
 * factorised by Cholesky; a pivot at most RANK_RTOL times its diagonal is a dependent row,
 * dropped (its unknown zero), as linalg.banded factorises S. */
struct schur { double L[M][M], Dc[M]; };

static inline void schur_factor(const struct mass *F, const double *G, struct schur *P) {
    double W[M][N], Sm[M][M];
    for (int i = 0; i < M; i++) forward(F, G + i * N, W[i]);
    for (int i = 0; i < M; i++)
        for (int j = 0; j <= i; j++) {
            double a = 0.0;
            for (int k = 0; k < N; k++) a += W[i][k] * W[j][k];
            Sm[i][j] = Sm[j][i] = a;
        }
    for (int i = 0; i < M; i++) P->Dc[i] = Sm[i][i] > 0 ? 1.0 / sqrt(Sm[i][i]) : 1.0;
    for (int i = 0; i < M; i++)
        for (int j = 0; j < M; j++) Sm[i][j] *= P->Dc[i] * P->Dc[j];
    for (int j = 0; j < M; j++) {
        double d = Sm[j][j];
        for (int k = 0; k < j; k++) d -= P->L[j][k] * P->L[j][k];
        P->L[j][j] = d > RANK_RTOL * Sm[j][j] ? sqrt(d) : 0.0;
        for (int i = j + 1; i < M; i++) {
            double a = Sm[i][j];
            for (int k = 0; k < j; k++) a -= P->L[i][k] * P->L[j][k];
            P->L[i][j] = P->L[j][j] != 0.0 ? a / P->L[j][j] : 0.0;
        }
        for (int i = 0; i < j; i++) P->L[i][j] = 0.0;
    }
}

/* x = S^-1 r */
static inline void schur_solve(const struct schur *P, const double *r, double *x) {
    double y[M];
    for (int i = 0; i < M; i++) {
        double a = r[i] * P->Dc[i];
        for (int k = 0; k < i; k++) a -= P->L[i][k] * y[k];
        y[i] = P->L[i][i] != 0.0 ? a / P->L[i][i] : 0.0;
    }
    for (int i = M - 1; i >= 0; i--) {
        double a = y[i];
        for (int k = i + 1; k < M; k++) a -= P->L[k][i] * x[k];
        x[i] = P->L[i][i] != 0.0 ? a / P->L[i][i] : 0.0;
    }
    for (int i = 0; i < M; i++) x[i] *= P->Dc[i];
}

/* --- Newton's method (integrators/newton.py) ----------------------------------------- */

/* integrators.newton.EXACT_WINDOW, KRYLOV_RTOL, KRYLOV_MAX_ITER */
static const double EXACT_WINDOW = 1e3;
static const double KRYLOV_RTOL = 1e-10;
static const int KRYLOV_MAX_ITER = 100;

/* The largest number of unknowns of the three methods (lobatto3ab3's). */
#define ZMAX (2 * S * N + S * M + N)

/* A method's stage system for Newton: the residual at z (which also keeps what the
 * correction at the same z reuses), simplified Newton's correction dz for a residual r at
 * the z of the last residual, the exact Jacobian's derivatives at z (linearize) and its
 * product J(z) x with them, and the magnitude of the residual's terms at z. The unknowns
 * and the residual are flat arrays of nz. */
struct system {
    void (*residual)(void *ctx, const double *z, double *r);
    void (*correction)(void *ctx, const double *r, double *dz);
    void (*linearize)(void *ctx, const double *z);
    void (*jacobian_times)(void *ctx, const double *x, double *out);
    double (*terms)(void *ctx, const double *z);
    void *ctx;
    int nz;
    int anderson;   /* simplified Newton's corrections mixed (integrators.newton.anderson_step) */
};

/* After an iteration: whether it was the last (*done: converged) from the new residual
 * norm r, the previous rp, the correction's norm dn, the terms' magnitude and the new
 * iterate's norm zn, with the window of the round-off floor and, for simplified Newton
 * (contracting), its two rules besides. Returns whether to go on. */
static inline int verdict(double r, double rp, double dn, double terms, double zn, double tol,
                          int it, int limit, double window, int contracting, int *done) {
    const double floor_r = EPS * (1.0 + terms);
    int halved = r <= 0.5 * rp;
    if (contracting) halved = halved && !(r <= floor_r && rp <= window * floor_r);
    const int stalled = !halved && r <= window * floor_r;
    *done = r <= tol || dn <= 4 * EPS * (1.0 + zn) || stalled;
    const int go = !*done && it < limit && isfinite(r);
    return contracting ? go && r <= 0.5 * rp : go;
}

static inline int all_finite(const double *x, int n) {
    for (int i = 0; i < n; i++)
        if (!isfinite(x[i])) return 0;
    return 1;
}

static inline double dot(const double *a, const double *b, int n) {
    double s = 0.0;
    for (int i = 0; i < n; i++) s += a[i] * b[i];
    return s;
}

/* Steps on which Newton with the exact Jacobian took over, and its BiCGSTAB iterations. */
static long exact_steps, krylov_iterations;

/* x -> -correction(x): the preconditioner, simplified Newton's inverse of J. */
static inline void precondition(const struct system *sys, const double *x, double *out) {
    sys->correction(sys->ctx, x, out);
    for (int i = 0; i < sys->nz; i++) out[i] = -out[i];
}

/* Preconditioned BiCGSTAB for J(z) x = b from x = 0 (linalg/krylov.py: the same
 * iteration, stop at ||r||_2 <= KRYLOV_RTOL ||b||_2, iteration cap and breakdowns). */
static void bicgstab(const struct system *sys, const double *b, double *x) {
    const int n = sys->nz;
    double r[ZMAX], p[ZMAX], v[ZMAX], s[ZMAX], t[ZMAX], ph[ZMAX], sh[ZMAX];
    const double floor_r = KRYLOV_RTOL * KRYLOV_RTOL * dot(b, b, n);
    double rho = 1.0, alpha = 1.0, omega = 1.0;
    for (int i = 0; i < n; i++) x[i] = 0.0, r[i] = p[i] = v[i] = b[i];
    int go = dot(b, b, n) > floor_r;
    for (int k = 0; go; k++) {
        krylov_iterations++;
        const double rho_new = dot(b, r, n);
        const double beta = rho_new / rho * alpha / omega;
        for (int i = 0; i < n; i++) p[i] = r[i] + beta * (p[i] - omega * v[i]);
        precondition(sys, p, ph);
        sys->jacobian_times(sys->ctx, ph, v);
        alpha = rho_new / dot(b, v, n);
        for (int i = 0; i < n; i++) s[i] = r[i] - alpha * v[i];
        if (dot(s, s, n) < floor_r) {   /* s small enough: the step ends at its first half */
            for (int i = 0; i < n; i++) x[i] += alpha * ph[i], r[i] = s[i];
            break;
        }
        precondition(sys, s, sh);
        sys->jacobian_times(sys->ctx, sh, t);
        omega = dot(t, s, n) / dot(t, t, n);
        for (int i = 0; i < n; i++) {
            x[i] += alpha * ph[i] + omega * sh[i];
            r[i] = s[i] - omega * t[i];
        }
        rho = rho_new;
        go = dot(r, r, n) > floor_r && k + 1 < KRYLOV_MAX_ITER && rho_new != 0
             && alpha != 0 && omega != 0;
    }
}

/* Simplified Newton from z (the first guess; the solution on return), its corrections
 * mixed by Anderson's method of depth one where the system asks for it, and where it does
 * not converge Newton with the exact Jacobian (matrix-free, BiCGSTAB preconditioned by the
 * simplified correction) for up to max_iter more iterations from the better of the first
 * guess and the last finite iterate. Returns the iterations, or -1 where neither
 * converged. */
static inline __attribute__((always_inline)) int newton(const struct system *sys, double *z,
                                                        double tol, int max_iter) {
    const int n = sys->nz;
    double z0[ZMAX], r0[ZMAX], r[ZMAX], dz[ZMAX];
    /* Anderson mixing's previous iterate, residual and correction. */
    double z_old[ZMAX], r_old[ZMAX], dz_old[ZMAX];
    int seen = 0;
    memcpy(z0, z, n * sizeof(double));
    sys->residual(sys->ctx, z, r0);
    memcpy(r, r0, n * sizeof(double));
    memcpy(z_old, z0, n * sizeof(double));
    memcpy(r_old, r0, n * sizeof(double));
    memset(dz_old, 0, n * sizeof(double));
    const double r0n = norm_of(r0, n);
    double rn = r0n;
    int it = 0, done = rn <= tol;
    int go = !done && max_iter > 0 && isfinite(rn);
    while (go) {
        const double terms = sys->terms(sys->ctx, z);
        sys->correction(sys->ctx, r, dz);
        if (sys->anderson) {
            /* dz - gamma (z - z_old + dz - dz_old), gamma = <dr, r> / <dr, dr>,
             * dr = r - r_old: 0 at the first iteration and where not finite. */
            double num = 0.0, den = 0.0;
            for (int i = 0; i < n; i++) {
                const double d = r[i] - r_old[i];
                num += d * r[i];
                den += d * d;
            }
            double gamma = seen && den > 0 ? num / den : 0.0;
            gamma = isfinite(gamma) ? gamma : 0.0;
            for (int i = 0; i < n; i++) {
                const double step = dz[i] - gamma * ((z[i] - z_old[i]) + (dz[i] - dz_old[i]));
                z_old[i] = z[i], r_old[i] = r[i], dz_old[i] = dz[i];
                dz[i] = step;
            }
            seen = 1;
        }
        for (int i = 0; i < n; i++) z[i] += dz[i];
        sys->residual(sys->ctx, z, r);
        const double rnew = norm_of(r, n);
        it++;
        go = verdict(rnew, rn, norm_of(dz, n), terms, norm_of(z, n), tol, it, max_iter,
                     WINDOW, 1, &done);
        rn = rnew;
    }
    if (done && all_finite(z, n)) return it;
    if (!(isfinite(rn) && rn < r0n)) {
        /* From the first guess; the residual again, for what the correction reuses. */
        memcpy(z, z0, n * sizeof(double));
        sys->residual(sys->ctx, z, r);
        rn = r0n;
    }
    const int limit = it + max_iter;
    exact_steps++;
    double b[ZMAX];
    done = rn <= tol;
    go = !done && it < limit && isfinite(rn);
    while (go) {
        const double terms = sys->terms(sys->ctx, z);
        for (int i = 0; i < n; i++) b[i] = -r[i];
        sys->linearize(sys->ctx, z);
        bicgstab(sys, b, dz);
        for (int i = 0; i < n; i++) z[i] += dz[i];
        sys->residual(sys->ctx, z, r);
        const double rnew = norm_of(r, n);
        it++;
        go = verdict(rnew, rn, norm_of(dz, n), terms, norm_of(z, n), tol, it, limit,
                     EXACT_WINDOW, 0, &done);
        rn = rnew;
    }
    return done && all_finite(z, n) ? it : -1;
}

/* --- the state every method carries -------------------------------------------------- */

struct state {
    double q[N], v[N], p[N];          /* p: rattle, lobatto3ab3 */
    double a[N], acc[N];              /* genalpha */
    double lam[M];                    /* the next step's first guess of the multipliers */
    struct mass F;                    /* M(q)'s factor (rattle, lobatto3ab3) */
    struct schur P;                   /* S's factor at q (rattle, lobatto3ab3) */
};

struct coefficients { double am, af, gamma, beta; };

/* --- RATTLE (integrators/rattle.py, the general position projection) -------------- */

struct rattle_z { double ph[N], q1[N], lam[M]; };
struct rattle_r { double r1[N], r2[N], r3[M]; };
struct rattle {
    const struct state *s;
    double G0[M * N], h;
    double Fv[N * N], Dm1[N * N], M1[N * N], G1[M * N];   /* the linearisation */
};

static void rattle_residual(void *ctx, const double *zf, double *rf) {
    const struct rattle *c = ctx;
    const struct rattle_z *z = (const struct rattle_z *)zf;
    struct rattle_r *r = (struct rattle_r *)rf;
    const double h = c->h;
    double vh[N], Fh[N], Gl[N], d[N], Md[N];
    mass_solve(&c->s->F, z->ph, vh);
    hamilton_force(c->s->q, vh, Fh);
    GT_times(c->G0, z->lam, Gl);
    for (int k = 0; k < N; k++) {
        r->r1[k] = z->ph[k] - c->s->p[k] - 0.5 * h * (Fh[k] - Gl[k]);
        d[k] = z->q1[k] - c->s->q[k] - 0.5 * h * vh[k];
    }
    struct config at;
    configuration(z->q1, (double *)&at);
    matvec(at.mass, N, N, N, d, Md, 0);
    mass_solve(&c->s->F, Md, Md);
    for (int k = 0; k < N; k++) r->r2[k] = Md[k] - 0.5 * h * vh[k];
    memcpy(r->r3, at.g, sizeof at.g);
}

/* Frozen at q0 without the force Jacobian: h^2/2 S0 dlam = r3 - G0 (r2 + h M^-1 r1). */
static void rattle_correction(void *ctx, const double *rf, double *df) {
    const struct rattle *c = ctx;
    const struct rattle_r *r = (const struct rattle_r *)rf;
    struct rattle_z *dz = (struct rattle_z *)df;
    const double h = c->h;
    double x[N], rhs[M], Gl[N];
    mass_solve(&c->s->F, r->r1, x);
    for (int k = 0; k < N; k++) x[k] = r->r2[k] + h * x[k];
    G_times(c->G0, x, rhs);
    for (int i = 0; i < M; i++) rhs[i] = r->r3[i] - rhs[i];
    schur_solve(&c->s->P, rhs, dz->lam);
    for (int i = 0; i < M; i++) dz->lam[i] *= 2.0 / (h * h);
    GT_times(c->G0, dz->lam, Gl);
    for (int k = 0; k < N; k++) dz->ph[k] = -r->r1[k] - 0.5 * h * Gl[k];
    mass_solve(&c->s->F, dz->ph, x);
    for (int k = 0; k < N; k++) dz->q1[k] = -r->r2[k] + h * x[k];
}

/* At z: dF/dv at (q0, v_1/2) and, at q1, d(M(q1) d)/dq1, M(q1) and G(q1). */
static void rattle_linearize(void *ctx, const double *zf) {
    struct rattle *c = ctx;
    const struct rattle_z *z = (const struct rattle_z *)zf;
    double vh[N], Fd[N * 2 * N], d[N];
    mass_solve(&c->s->F, z->ph, vh);
    hamilton_force_d(c->s->q, vh, Fd);
    for (int i = 0; i < N; i++)
        for (int k = 0; k < N; k++) c->Fv[i * N + k] = Fd[i * 2 * N + N + k];
    for (int k = 0; k < N; k++) d[k] = z->q1[k] - c->s->q[k] - 0.5 * c->h * vh[k];
    mass_dq(z->q1, d, c->Dm1);
    mass_matrix(z->q1, c->M1);
    constraint_jacobian(z->q1, c->G1);
}

static void rattle_jacobian_times(void *ctx, const double *xf, double *of) {
    const struct rattle *c = ctx;
    const struct rattle_z *x = (const struct rattle_z *)xf;
    struct rattle_r *o = (struct rattle_r *)of;
    const double h = c->h;
    double dvh[N], dF[N], Gl[N], dd[N], a[N];
    mass_solve(&c->s->F, x->ph, dvh);
    matvec(c->Fv, N, N, N, dvh, dF, 0);
    GT_times(c->G0, x->lam, Gl);
    for (int k = 0; k < N; k++) {
        o->r1[k] = x->ph[k] - 0.5 * h * (dF[k] - Gl[k]);
        dd[k] = x->q1[k] - 0.5 * h * dvh[k];
    }
    matvec(c->Dm1, N, N, N, x->q1, a, 0);
    matvec(c->M1, N, N, N, dd, a, 1);
    mass_solve(&c->s->F, a, a);
    for (int k = 0; k < N; k++) o->r2[k] = a[k] - 0.5 * h * dvh[k];
    G_times(c->G1, x->q1, o->r3);
}

static double rattle_terms(void *ctx, const double *z) {
    (void)ctx;
    return norm_of(z, (int)(sizeof(struct rattle_z) / sizeof(double)));
}

static inline int rattle_step(struct state *s, double h, double tol, int max_iter) {
    struct rattle c = {.s = s, .h = h};
    const struct system sys = {rattle_residual, rattle_correction, rattle_linearize,
                               rattle_jacobian_times, rattle_terms, &c,
                               (int)(sizeof(struct rattle_z) / sizeof(double)), 0};
    struct rattle_z z;
    double x[N];
    constraint_jacobian(s->q, c.G0);
    mass_solve(&s->F, s->p, x);
    for (int k = 0; k < N; k++) {
        z.ph[k] = s->p[k];
        z.q1[k] = s->q[k] + h * x[k];
    }
    memcpy(z.lam, s->lam, sizeof z.lam);
    const int it = newton(&sys, (double *)&z, tol, max_iter);
    if (it < 0) return -1;
    /* The velocity projection at q1 (linear in mu), with M(q1) and S(q1) factorised once. */
    double vh[N], F1[N], base[N], rhs[M], mu[M], Gm[N];
    struct config at;
    memcpy(s->q, z.q1, sizeof s->q);
    configuration(s->q, (double *)&at);
    const double *G1 = at.G;
    cholesky(at.mass, &s->F);
    mass_solve(&s->F, z.ph, vh);
    hamilton_force(s->q, vh, F1);
    for (int k = 0; k < N; k++) base[k] = z.ph[k] + 0.5 * h * F1[k];
    mass_solve(&s->F, base, x);
    G_times(G1, x, rhs);
    schur_factor(&s->F, G1, &s->P);
    schur_solve(&s->P, rhs, mu);
    for (int i = 0; i < M; i++) mu[i] *= 2.0 / h;
    GT_times(G1, mu, Gm);
    for (int k = 0; k < N; k++) s->p[k] = base[k] - 0.5 * h * Gm[k];
    mass_solve(&s->F, s->p, s->v);
    /* The next step's first guess of lambda is mu (integrators/rattle.py). */
    memcpy(s->lam, mu, sizeof mu);
    return it;
}

/* p0 = M(q0) v0, the factors of M and S at q0, lambda = 0 (rattle and lobatto3ab3). */
static void momentum_start(struct state *s) {
    double G0[M * N];
    mass_times(s->q, s->v, s->p);
    mass_factor(s->q, &s->F);
    constraint_jacobian(s->q, G0);
    schur_factor(&s->F, G0, &s->P);
    for (int i = 0; i < M; i++) s->lam[i] = 0.0;
}

/* --- generalized-alpha, index 3 (integrators/genalpha.py) --------------------------- */

struct alpha_z { double x[N], Lam[M]; };
struct alpha_r { double rM[N], rg[M]; };

struct alpha {
    struct coefficients c;
    double h, bh2, w, cm, data;
    double q_hat[N], v_hat[N], acc_hat[N];
    struct mass F;                    /* M(q_n), S(q_n) and G(q_n): the frozen matrix */
    struct schur P;
    double G0[M * N];
    double Jx[N * N], G1[M * N];      /* the linearisation: d r_M / dx, G(q_n+1) */
};

static inline void alpha_kinematics(const struct alpha *k, const struct alpha_z *z,
                                    double *q1, double *v1, double *acc1) {
    for (int j = 0; j < N; j++) {
        q1[j] = k->q_hat[j] + z->x[j];
        v1[j] = k->v_hat[j] + (k->c.gamma / (k->c.beta * k->h)) * z->x[j];
        acc1[j] = ((1 - k->c.am) * z->x[j] + k->acc_hat[j]) / (1 - k->c.af);
    }
}

static void alpha_residual(void *ctx, const double *zf, double *rf) {
    const struct alpha *k = ctx;
    const struct alpha_z *z = (const struct alpha_z *)zf;
    struct alpha_r *r = (struct alpha_r *)rf;
    double q1[N], v1[N], acc1[N], Ma[N], f[N], Gl[N];
    struct config at;
    alpha_kinematics(k, z, q1, v1, acc1);
    configuration(q1, (double *)&at);
    matvec(at.mass, N, N, N, acc1, Ma, 0);
    lagrange_force(q1, v1, f);
    GT_times(at.G, z->Lam, Gl);
    for (int j = 0; j < N; j++) r->rM[j] = k->w * (Ma[j] - k->bh2 * f[j] + Gl[j]);
    memcpy(r->rg, at.g, sizeof at.g);
}

/* [c M, G0^T; G0, 0] at q_n on the rows divided back by w: S0 dLam = c r_g - G0 M^-1 r_M,
 * dx = -M^-1 (r_M + G0^T dLam) / c. */
static void alpha_correction(void *ctx, const double *rf, double *df) {
    const struct alpha *k = ctx;
    const struct alpha_r *r = (const struct alpha_r *)rf;
    struct alpha_z *dz = (struct alpha_z *)df;
    double MinvR[N], rhs[M], Gl[N];
    for (int j = 0; j < N; j++) MinvR[j] = r->rM[j] / k->w;
    mass_solve(&k->F, MinvR, MinvR);
    G_times(k->G0, MinvR, rhs);
    for (int i = 0; i < M; i++) rhs[i] = k->cm * r->rg[i] - rhs[i];
    schur_solve(&k->P, rhs, dz->Lam);
    GT_times(k->G0, dz->Lam, Gl);
    mass_solve(&k->F, Gl, Gl);
    for (int j = 0; j < N; j++) dz->x[j] = -(MinvR[j] + Gl[j]) / k->cm;
}

/* d r_M / dx = w (d(M acc1)/dq + c_a M - bh2 (df/dq + c_v df/dv) + d(G^T Lam)/dq) with
 * c_v = gamma / (beta h), c_a = (1 - alpha_m) / (1 - alpha_f); d r_M / dLam = w G1^T;
 * d r_g / dx = G1. */
static void alpha_linearize(void *ctx, const double *zf) {
    struct alpha *k = ctx;
    const struct alpha_z *z = (const struct alpha_z *)zf;
    const double wv = k->c.gamma / (k->c.beta * k->h), wa = (1 - k->c.am) / (1 - k->c.af);
    double q1[N], v1[N], acc1[N], Dm[N * N], M1[N * N], Fd[N * 2 * N], Gt[N * N];
    alpha_kinematics(k, z, q1, v1, acc1);
    mass_dq(q1, acc1, Dm);
    mass_matrix(q1, M1);
    lagrange_force_d(q1, v1, Fd);
    gt_dq(q1, z->Lam, Gt);
    constraint_jacobian(q1, k->G1);
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++)
            k->Jx[i * N + j] = k->w * (Dm[i * N + j] + wa * M1[i * N + j]
                                       - k->bh2 * (Fd[i * 2 * N + j] + wv * Fd[i * 2 * N + N + j])
                                       + Gt[i * N + j]);
}

static void alpha_jacobian_times(void *ctx, const double *xf, double *of) {
    const struct alpha *k = ctx;
    const struct alpha_z *x = (const struct alpha_z *)xf;
    struct alpha_r *o = (struct alpha_r *)of;
    double Gl[N];
    GT_times(k->G1, x->Lam, Gl);
    matvec(k->Jx, N, N, N, x->x, o->rM, 0);
    for (int j = 0; j < N; j++) o->rM[j] += k->w * Gl[j];
    G_times(k->G1, x->x, o->rg);
}

static double alpha_terms(void *ctx, const double *z) {
    const struct alpha *k = ctx;
    return fmax(k->w * norm_of(z, (int)(sizeof(struct alpha_z) / sizeof(double))), k->data);
}

static inline int genalpha_step(struct state *s, struct coefficients c, double h, double tol,
                                int max_iter) {
    struct alpha k = {.c = c, .h = h};
    /* Anderson mixing on, as integrators/genalpha.py asks newton() for it. */
    const struct system sys = {alpha_residual, alpha_correction, alpha_linearize,
                               alpha_jacobian_times, alpha_terms, &k,
                               (int)(sizeof(struct alpha_z) / sizeof(double)), 1};
    struct alpha_z z;
    k.bh2 = c.beta * h * h;
    k.w = c.gamma / (c.beta * h);
    k.cm = (1 - c.am) / (1 - c.af);
    for (int j = 0; j < N; j++) {
        k.q_hat[j] = s->q[j] + h * s->v[j] + h * h * (0.5 - c.beta) * s->a[j];
        k.v_hat[j] = s->v[j] + h * (1 - c.gamma) * s->a[j];
        k.acc_hat[j] = k.bh2 * (c.am * s->a[j] - c.af * s->acc[j]);
    }
    /* The iteration matrix at q_n, factorised once per step. */
    struct config at;
    configuration(s->q, (double *)&at);
    cholesky(at.mass, &k.F);
    memcpy(k.G0, at.G, sizeof k.G0);
    schur_factor(&k.F, k.G0, &k.P);
    /* The rounding of g(q): max_i sum_j |G_ij| |q_j| (Mechanics.rounding). */
    k.data = 0.0;
    for (int i = 0; i < M; i++) {
        double a = 0.0;
        for (int j = 0; j < N; j++) a += fabs(k.G0[i * N + j]) * fabs(s->q[j]);
        k.data = a > k.data ? a : k.data;
    }
    for (int j = 0; j < N; j++) z.x[j] = k.bh2 * s->a[j];
    for (int i = 0; i < M; i++) z.Lam[i] = k.bh2 * s->lam[i];
    const int it = newton(&sys, (double *)&z, tol, max_iter);
    if (it < 0) return -1;
    double acc1[N];
    alpha_kinematics(&k, &z, s->q, s->v, acc1);
    for (int j = 0; j < N; j++) {
        s->a[j] = z.x[j] / k.bh2;
        s->acc[j] = acc1[j] / k.bh2;
    }
    for (int i = 0; i < M; i++) s->lam[i] = z.Lam[i] / k.bh2;
    return it;
}

/* Consistent a_0 = acc_0 and lambda_0 from the index-1 system (Mechanics.accelerations). */
static void genalpha_start(struct state *s) {
    struct mass F;
    struct schur P;
    double G0[M * N], MinvF[N], rhs[M], gam[M], Gl[N];
    mass_factor(s->q, &F);
    lagrange_force(s->q, s->v, MinvF);
    mass_solve(&F, MinvF, MinvF);
    constraint_jacobian(s->q, G0);
    G_times(G0, MinvF, rhs);
    curvature(s->q, s->v, gam);
    for (int i = 0; i < M; i++) rhs[i] += gam[i];
    schur_factor(&F, G0, &P);
    schur_solve(&P, rhs, s->lam);
    GT_times(G0, s->lam, Gl);
    mass_solve(&F, Gl, Gl);
    for (int j = 0; j < N; j++) s->a[j] = s->acc[j] = MinvF[j] - Gl[j];
}

/* --- Lobatto IIIA-IIIB (integrators/lobatto.py, structured path) -------------------- */

struct lobatto_z { double Q[S][N], V[S][N], Lam[S][M], v1[N]; };
struct lobatto_r { double RQ[S][N], RP[S][N], Rp[N], Rg[S - 1][M], Rv[M]; };
struct lobatto {
    const struct state *s;
    double h;
    /* G at the stage positions and at q1 of the iterate of the last residual. */
    double GQ[S][M * N], G1[M * N];
    /* The linearisation: per stage M(Q_j), d(M V_j)/dQ_j, [dU/dQ_j, dU/dV_j] without the
     * G^T dLam part; at q1 M(q1), d(M v1)/dq1 and d(G v1)/dq1. */
    double MQ[S][N * N], DmQ[S][N * N], UQ[S][N * N], UV[S][N * N];
    double M1[N * N], Dm1[N * N], Gv1[M * N];
};

static inline void end_position(const double *q0, const struct lobatto_z *z, double h,
                                double *q1) {
    for (int k = 0; k < N; k++) {
        double a = 0.0;
        for (int j = 0; j < S; j++) a += B[j] * z->V[j][k];
        q1[k] = q0[k] + h * a;
    }
}

static void lobatto_residual(void *ctx, const double *zf, double *rf) {
    struct lobatto *c = ctx;
    const struct lobatto_z *z = (const struct lobatto_z *)zf;
    struct lobatto_r *r = (struct lobatto_r *)rf;
    const double *q0 = c->s->q, *p0 = c->s->p, h = c->h;
    double U[S][N], q1[N], Mv[N];
    struct config at;
    for (int j = 0; j < S; j++) {
        double f[N], Gl[N];
        configuration(z->Q[j], (double *)&at);
        matvec(at.mass, N, N, N, z->V[j], r->RP[j], 0);    /* P_j, completed below */
        hamilton_force(z->Q[j], z->V[j], f);
        memcpy(c->GQ[j], at.G, sizeof at.G);
        GT_times(c->GQ[j], z->Lam[j], Gl);
        for (int k = 0; k < N; k++) U[j][k] = f[k] - Gl[k];
        if (j > 0) memcpy(r->Rg[j - 1], at.g, sizeof at.g);
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
            r->RP[j][k] = r->RP[j][k] - p0[k] - h * ah;
        }
    configuration(q1, (double *)&at);
    matvec(at.mass, N, N, N, z->v1, Mv, 0);
    for (int k = 0; k < N; k++) {
        double b = 0.0;
        for (int l = 0; l < S; l++) b += B[l] * U[l][k];
        r->Rp[k] = Mv[k] - p0[k] - h * b;
    }
    memcpy(c->G1, at.G, sizeof at.G);
    G_times(c->G1, z->v1, r->Rv);
}

/* S_0 X B^T = R through the factor of S at q0, G at the current stage positions where it
 * multiplies a residual (integrators/lobatto.py, LobattoIIIAIIIB.simplified). */
static void lobatto_correction(void *ctx, const double *rf, double *df) {
    const struct lobatto *c = ctx;
    const struct lobatto_r *r = (const struct lobatto_r *)rf;
    struct lobatto_z *dz = (struct lobatto_z *)df;
    const struct mass *F = &c->s->F;
    const double h = c->h;
    double MinvRP[S][N], x[N], y[M], rhs[S][M], X[S][M], force[S][N];
    for (int j = 0; j < S; j++) mass_solve(F, r->RP[j], MinvRP[j]);
    for (int i = 1; i < S; i++) {
        for (int k = 0; k < N; k++) {
            double a = 0.0;
            for (int l = 0; l < S; l++)
                if (A[i][l] != 0.0) a += A[i][l] * MinvRP[l][k];
            x[k] = r->RQ[i][k] + h * a;
        }
        G_times(c->GQ[i], x, y);
        for (int m = 0; m < M; m++) rhs[i - 1][m] = (r->Rg[i - 1][m] - y[m]) * (1.0 / (h * h));
    }
    mass_solve(F, r->Rp, x);
    G_times(c->G1, x, y);
    for (int m = 0; m < M; m++) rhs[S - 1][m] = (r->Rv[m] - y[m]) * (1.0 / h);
    for (int i = 0; i < S; i++) schur_solve(&c->s->P, rhs[i], X[i]);
    for (int i = 0; i < S; i++) {
        for (int m = 0; m < M; m++) {
            double a = 0.0;
            for (int l = 0; l < S; l++)
                if (BINV[i][l] != 0.0) a += BINV[i][l] * X[l][m];
            dz->Lam[i][m] = a;
        }
        GT_times(c->GQ[i], dz->Lam[i], force[i]);
    }
    for (int j = 0; j < S; j++) {
        for (int k = 0; k < N; k++) {
            double ah = 0.0;
            for (int l = 0; l < S; l++)
                if (AH[j][l] != 0.0) ah += AH[j][l] * force[l][k];
            x[k] = -r->RP[j][k] - h * ah;
        }
        mass_solve(F, x, dz->V[j]);
    }
    for (int j = 0; j < S; j++)
        for (int k = 0; k < N; k++) {
            double a = 0.0;
            for (int l = 0; l < S; l++)
                if (A[j][l] != 0.0) a += A[j][l] * dz->V[l][k];
            dz->Q[j][k] = -r->RQ[j][k] + h * a;
        }
    for (int k = 0; k < N; k++) {
        double b = 0.0;
        for (int l = 0; l < S; l++) b += B[l] * force[l][k];
        x[k] = -r->Rp[k] - h * b;
    }
    mass_solve(F, x, dz->v1);
}

/* The derivatives at z; G at z as the last residual left it. */
static void lobatto_linearize(void *ctx, const double *zf) {
    struct lobatto *c = ctx;
    const struct lobatto_z *z = (const struct lobatto_z *)zf;
    double q1[N], Fd[N * 2 * N], Gt[N * N];
    for (int j = 0; j < S; j++) {
        mass_matrix(z->Q[j], c->MQ[j]);
        mass_dq(z->Q[j], z->V[j], c->DmQ[j]);
        hamilton_force_d(z->Q[j], z->V[j], Fd);
        gt_dq(z->Q[j], z->Lam[j], Gt);
        for (int i = 0; i < N; i++)
            for (int k = 0; k < N; k++) {
                c->UQ[j][i * N + k] = Fd[i * 2 * N + k] - Gt[i * N + k];
                c->UV[j][i * N + k] = Fd[i * 2 * N + N + k];
            }
    }
    end_position(c->s->q, z, c->h, q1);
    mass_matrix(q1, c->M1);
    mass_dq(q1, z->v1, c->Dm1);
    gv_dq(q1, z->v1, c->Gv1);
}

static void lobatto_jacobian_times(void *ctx, const double *xf, double *of) {
    const struct lobatto *c = ctx;
    const struct lobatto_z *x = (const struct lobatto_z *)xf;
    struct lobatto_r *o = (struct lobatto_r *)of;
    const double h = c->h;
    double dU[S][N], dq1[N], Gl[N];
    for (int j = 0; j < S; j++) {
        matvec(c->DmQ[j], N, N, N, x->Q[j], o->RP[j], 0);   /* dP_j, completed below */
        matvec(c->MQ[j], N, N, N, x->V[j], o->RP[j], 1);
        matvec(c->UQ[j], N, N, N, x->Q[j], dU[j], 0);
        matvec(c->UV[j], N, N, N, x->V[j], dU[j], 1);
        GT_times(c->GQ[j], x->Lam[j], Gl);
        for (int k = 0; k < N; k++) dU[j][k] -= Gl[k];
    }
    for (int k = 0; k < N; k++) {
        double s = 0.0;
        for (int j = 0; j < S; j++) s += B[j] * x->V[j][k];
        dq1[k] = h * s;
    }
    for (int j = 0; j < S; j++)
        for (int k = 0; k < N; k++) {
            double av = 0.0, ah = 0.0;
            for (int l = 0; l < S; l++) {
                if (A[j][l] != 0.0) av += A[j][l] * x->V[l][k];
                if (AH[j][l] != 0.0) ah += AH[j][l] * dU[l][k];
            }
            o->RQ[j][k] = x->Q[j][k] - h * av;
            o->RP[j][k] -= h * ah;
        }
    matvec(c->Dm1, N, N, N, dq1, o->Rp, 0);
    matvec(c->M1, N, N, N, x->v1, o->Rp, 1);
    for (int k = 0; k < N; k++) {
        double s = 0.0;
        for (int l = 0; l < S; l++) s += B[l] * dU[l][k];
        o->Rp[k] -= h * s;
    }
    for (int i = 1; i < S; i++) G_times(c->GQ[i], x->Q[i], o->Rg[i - 1]);
    matvec(c->Gv1, M, N, N, dq1, o->Rv, 0);
    matvec(c->G1, M, N, N, x->v1, o->Rv, 1);
}

static double lobatto_terms(void *ctx, const double *z) {
    const struct lobatto *c = ctx;
    return fmax(norm_of(z, (int)(sizeof(struct lobatto_z) / sizeof(double))),
                norm_of(c->s->p, N));
}

static inline int lobatto_step(struct state *s, double h, double tol, int max_iter) {
    struct lobatto c = {.s = s, .h = h};
    const struct system sys = {lobatto_residual, lobatto_correction, lobatto_linearize,
                               lobatto_jacobian_times, lobatto_terms, &c,
                               (int)(sizeof(struct lobatto_z) / sizeof(double)), 0};
    struct lobatto_z z;
    for (int j = 0; j < S; j++) {
        for (int k = 0; k < N; k++) {
            z.Q[j][k] = s->q[k] + h * C[j] * s->v[k];
            z.V[j][k] = s->v[k];
        }
        memcpy(z.Lam[j], s->lam, sizeof z.Lam[j]);
    }
    memcpy(z.v1, s->v, sizeof z.v1);
    const int it = newton(&sys, (double *)&z, tol, max_iter);
    if (it < 0) return -1;
    end_position(s->q, &z, h, s->q);
    memcpy(s->v, z.v1, sizeof s->v);
    struct config at;
    configuration(s->q, (double *)&at);
    matvec(at.mass, N, N, N, s->v, s->p, 0);
    memcpy(s->lam, z.Lam[S - 1], sizeof s->lam);
    /* The next step's M(q0) and S_0 factors. */
    cholesky(at.mass, &s->F);
    schur_factor(&s->F, at.G, &s->P);
    return it;
}

/* --- the loop ------------------------------------------------------------------------ */

static inline double energy_of(const double *q, const double *v) {
    double e[1];
    energy(q, v, e);
    return e[0];
}

/* The solve from (q0, v0): n steps of h; the final state into s, the maxima into mx.
 * Returns the Newton iterations, or -(the failing step) where Newton failed. */
static long solve(enum method method, struct coefficients c, long n, double h, double tol,
                  int max_iter, const double *q0, const double *v0, struct state *s,
                  double *mx) {
    static double win[NWIN][3];
    long iterations = 0;
    exact_steps = krylov_iterations = 0;
    memset(win, 0, sizeof win);
    memset(s, 0, sizeof *s);
    memcpy(s->q, q0, sizeof s->q);
    memcpy(s->v, v0, sizeof s->v);
    if (method == GENALPHA) genalpha_start(s);
    else momentum_start(s);
    const double H0 = energy_of(q0, v0);
    for (long k = 0; k < n; k++) {
        int it;
        if (method == GENALPHA) it = genalpha_step(s, c, h, tol, max_iter);
        else if (method == RATTLE) it = rattle_step(s, h, tol, max_iter);
        else it = lobatto_step(s, h, tol, max_iter);
        if (it < 0) return -(k + 1);
        iterations += it;
        struct config at;
        double Gv[M];
        configuration(s->q, (double *)&at);
        G_times(at.G, s->v, Gv);
        const double m[3] = {norm_of(at.g, M), norm_of(Gv, M),
                             fabs(energy_of(s->q, s->v) - H0)};
        double *row = win[k * NWIN / n];
        for (int j = 0; j < 3; j++) row[j] = m[j] > row[j] ? m[j] : row[j];
    }
    for (int j = 0; j < 3; j++) mx[j] = 0.0;
    for (int i = 0; i < NWIN; i++)
        for (int j = 0; j < 3; j++) mx[j] = win[i][j] > mx[j] ? win[i][j] : mx[j];
    return iterations;
}

int main(int argc, char **argv) {
    enum method method = RATTLE;
    long n, max_iter, repeats;
    double h, tol, q0[N], v0[N];
    struct coefficients c;
    int ok = argc == 11 + 2 * N && parse_long(argv[2], &n) && parse_double(argv[3], &h)
             && h > 0 && parse_double(argv[4], &tol) && tol > 0
             && parse_long(argv[5], &max_iter) && parse_long(argv[6], &repeats)
             && parse_double(argv[7], &c.am) && parse_double(argv[8], &c.af)
             && parse_double(argv[9], &c.gamma) && parse_double(argv[10], &c.beta);
    for (int k = 0; ok && k < N; k++)
        ok = parse_double(argv[11 + k], &q0[k]) && parse_double(argv[11 + N + k], &v0[k]);
    if (ok && strcmp(argv[1], "rattle") == 0) {
        method = RATTLE;
    } else if (ok && strcmp(argv[1], "genalpha") == 0 && c.beta > 0 && c.af != 1.0) {
        method = GENALPHA;
    } else if (ok && strcmp(argv[1], "lobatto3ab3") == 0) {
        method = LOBATTO;
    } else {
        fprintf(stderr, "usage: %s rattle|genalpha|lobatto3ab3 N_STEPS H NEWTON_TOL MAX_ITER "
                        "REPEATS AM AF GAMMA BETA q_1..q_%d v_1..v_%d (N_STEPS, MAX_ITER, "
                        "REPEATS whole numbers >= 1; H, NEWTON_TOL > 0; genalpha: BETA > 0, "
                        "AF != 1)\n", argc > 0 ? argv[0] : "dense_andrews", N, N);
        return 2;
    }
    struct state s;
    double mx[3] = {0.0, 0.0, 0.0};
    double best = INFINITY, best_cpu = INFINITY;
    long iterations = 0;
    for (long r = 0; r < repeats; r++) {
        const double t0 = seconds_of(CLOCK_MONOTONIC), c0 = seconds_of(CLOCK_PROCESS_CPUTIME_ID);
        iterations = solve(method, c, n, h, tol, (int)max_iter, q0, v0, &s, mx);
        const double c1 = seconds_of(CLOCK_PROCESS_CPUTIME_ID), t1 = seconds_of(CLOCK_MONOTONIC);
        if (iterations < 0) {
            fprintf(stderr, "%s: Newton did not converge at step %ld\n", argv[1], -iterations);
            return 1;
        }
        best = fmin(best, t1 - t0);
        best_cpu = fmin(best_cpu, c1 - c0);
    }
    printf("steps %ld\nnewton %ld\nexact_steps %ld\nkrylov %ld\nseconds %.9f\n"
           "cpu_seconds %.9f\n", n, iterations, exact_steps, krylov_iterations, best, best_cpu);
    printf("y");
    for (int k = 0; k < N; k++) printf(" %.17g", s.q[k]);
    for (int k = 0; k < N; k++) printf(" %.17g", s.v[k]);
    printf("\nmax %.3e %.3e %.3e\n", mx[0], mx[1], mx[2]);
    return 0;
}
