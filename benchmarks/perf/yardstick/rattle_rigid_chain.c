/* Speed-of-light yardstick for cost against size: RATTLE on the rigid chain in plain C, O(N).
 *
 * The physics of problems/rigid_chain.py at its default parameters: N rigid bodies of mass
 * m_b = 1 and principal inertia J = (0.09, 0.11, 0.04), with joint points s+- = (0, 0, +-l),
 * l = 0.5, on their body z axes, hang under gravity g0 = 9.81 (along -z) from a spherical
 * joint at the origin, each joined to the next by a spherical joint. Coordinates body by
 * body, q = (x_1, e_1, ..., x_N, e_N) (n = 7N), e_k the Euler parameters (unit quaternion,
 * scalar first) of the rotation R(e_k) from body to space axes. The initial state is that
 * module's initial_state (a crooked helix, theta0 = 0.6, swirling at precession = 1 and
 * spinning at spin = 4 rad/s), ported below, so the program reads no input.
 *
 * The mechanics, derived by hand here (the suite differentiates the module's functions):
 * with A(e) = (e^T; E(e)) (4 x 4, E of problems/rigid_body.py, omega = 2 E(e) e'), whose rows
 * are orthogonal with norm |e| for any e, and D = diag(j0, J_1, J_2, J_3), j0 = mean(J),
 *   - mass block of body k: diag(m_b I3, M_e) with M_e = 4 E^T J E + 4 j0 e e^T = 4 A^T D A
 *     (4 E^T J E the Euler-parameter mass of Nikravesh 1988, 4 j0 e e^T the term the module
 *     adds to make it definite), so that
 *     M_e^{-1} = A^T D^{-1} A / (4 |e|^4) in closed form, no factorisation;
 *   - T = sum_k m_b |x_k'|^2 / 2 + 2 a_k^T D a_k with a = A(e) e'. Since E(e) e' = -E(e') e,
 *     dT/de = 4 (j0 a_0 e' - E(e')^T J a_{1:3}) and dT/dx = 0; U = m_b g0 sum_k z_k;
 *     F(q, p) = -H_q(q, p) = -grad U + dT/dq(q, v) at v = M(q)^{-1} p (problems/mechanics.py);
 *   - constraints body by body: e_k . e_k - 1, then u_k - w_{k-1} (3 rows) with
 *     u_k = x_k + l c(e_k), w_k = x_k - l c(e_k), w_0 = 0, c(e) = R(e) e_z. With
 *     C(e) = dc/de (3 x 4), body k's rows of G are (0, 2 e_k^T) and (I3, l C(e_k)) in body k's
 *     columns and (-I3, l C(e_{k-1})) in body k-1's: G is block bidiagonal;
 *   - S = G M^{-1} G^T is block tridiagonal with 4 x 4 blocks. With Q_k = G_kk M_k^{-1} G_kk^T,
 *     S_kk = Q_k + Q_{k-1} on rows and columns 1..3, and S_{k,k-1} is zero in row 0 and equal
 *     to Q_{k-1} in rows 1..3 but for -2 I3 / m_b on columns 1..3 (the x part of body k-1's
 *     rows changes sign). S is factorised by block Cholesky, L_kk L_kk^T = S_kk - L_{k,k-1}
 *     L_{k,k-1}^T, L_{k,k-1} = S_{k,k-1} L_{k-1,k-1}^{-T}: safe without pivoting, S being
 *     symmetric positive definite wherever G has full row rank (a chain always has).
 * These were checked against the suite's autodiff of the module's functions.
 *
 * One step is the step integrators/rattle.py takes on its structured path for this
 * non-separable Hamiltonian (position_structured, then the velocity projection of step):
 *   - position projection: simplified Newton (integrators/newton.py) on z = (p_half, q1, lam),
 *       r1 = p_half - p0 - h/2 (F(q0, p_half) - G(q0)^T lam),
 *       r2 = q1 - q0 - h/2 (M(q0)^{-1} + M(q1)^{-1}) p_half,      r3 = g(q1),
 *     (rattle takes r2 times M(q0)^{-1} M(q1): the same roots and the same correction
 *     formula, without factorising M(q1) at every iterate; here M^{-1} is in closed form),
 *     from z0 = (p0, q0 + h M(q0)^{-1} p0, the previous step's mu; zeros at the start), with
 *     the Jacobian frozen at q0 without the force Jacobian: h^2/2 S0 dlam = r3 - G0 (r2 + h
 *     M0^{-1} r1), dp = -r1 - h/2 G0^T dlam, dq = -r2 + h M0^{-1} dp, S0 the previous step's
 *     velocity-projection factor. Newton's test as there: converged at |r| <= tol, at a
 *     correction |dz| <= 4 eps (1 + |z|), or stalled within 8 times the floor eps (1 +
 *     |z_before|): less than halved, or at the floor after a residual within those 8
 *     times; it goes on only while each iteration halves |r|, for up to
 *     50 corrections (max-norms over all of z, r and dz). Where rattle would then hand over
 *     to Newton with the exact Jacobian (Krylov), this program reports failure instead.
 *   - velocity projection: with base = p_half + h/2 F(q1, p_half), factorise S1 = S(q1) and
 *     solve (h/2) S1 mu = G(q1) M(q1)^{-1} base; p1 = base - h/2 G(q1)^T mu. S1 is the next
 *     step's S0 and mu its first guess of lam.
 *   - bookkeeping: |g|, |G v| (max-norms) and |H - H0| (H = T + U, v = M^{-1} p) after every
 *     step, folded into per-window maxima (min(N_STEPS, 1000) windows), as the suite does.
 * Every operation is a sweep over the bodies: O(N) per Newton iteration and per step.
 *
 * usage: rattle_rigid_chain N_BODIES N_STEPS H [NEWTON_TOL [state]]  (tolerance default
 *        1e-16, as rattle's; "state" also prints the final q and v, one line each)
 *     -> "steps seconds cpu_seconds max_g max_gv max_dH newton_iterations peak_kib"
 * (seconds: wall clock of the time loop; cpu_seconds: this process's CPU time in it; set-up
 * and allocation are outside both; newton_iterations: corrections summed over the steps;
 * peak_kib: the peak resident set since the program started, VmHWM, -1 where /proc does
 * not give it). Exit status 2 on bad arguments, 1 when Newton or the factorisation fails.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "yardstick.h"

#define MAX_WINDOWS 1000
#define MAX_ITER 50            /* rattle's newton_max_iter */
#define SIMPLIFIED_WINDOW 8.0  /* integrators/newton.py */

static const double MASS = 1.0, HALF_LENGTH = 0.5, GRAVITY = 9.81;
static const double J[3] = {0.09, 0.11, 0.04};
static const double THETA0 = 0.6, PRECESSION = 1.0, SPIN = 4.0, PHI_STEP = 0.9, PSI_STEP = 0.4;
static const double EPS = 2.220446049250313e-16;
static double D[4], Dinv[4]; /* (j0, J_1, J_2, J_3) and reciprocals, set in main */

/* a = A(e) x = (e . x, E(e) x). */
static inline void a_times(const double *e, const double *x, double *a) {
    a[0] = e[0] * x[0] + e[1] * x[1] + e[2] * x[2] + e[3] * x[3];
    a[1] = -e[1] * x[0] + e[0] * x[1] + e[3] * x[2] - e[2] * x[3];
    a[2] = -e[2] * x[0] - e[3] * x[1] + e[0] * x[2] + e[1] * x[3];
    a[3] = -e[3] * x[0] + e[2] * x[1] - e[1] * x[2] + e[0] * x[3];
}

/* x = s A(e)^T a. */
static inline void at_times(const double *e, const double *a, double s, double *x) {
    x[0] = s * (e[0] * a[0] - e[1] * a[1] - e[2] * a[2] - e[3] * a[3]);
    x[1] = s * (e[1] * a[0] + e[0] * a[1] - e[3] * a[2] + e[2] * a[3]);
    x[2] = s * (e[2] * a[0] + e[3] * a[1] + e[0] * a[2] - e[1] * a[3]);
    x[3] = s * (e[3] * a[0] - e[2] * a[1] + e[1] * a[2] + e[0] * a[3]);
}

/* c(e) = R(e) e_z and C(e) = dc/de (3 x 4, linear in e). */
static inline void axis(const double *e, double *c) {
    c[0] = 2 * (e[1] * e[3] + e[0] * e[2]);
    c[1] = 2 * (e[2] * e[3] - e[0] * e[1]);
    c[2] = e[0] * e[0] - e[1] * e[1] - e[2] * e[2] + e[3] * e[3];
}
static inline void axis_jacobian(const double *e, double C[3][4]) {
    const double r[3][4] = {{e[2], e[3], e[0], e[1]}, {-e[1], -e[0], e[3], e[2]},
                            {e[0], -e[1], -e[2], e[3]}};
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 4; j++) C[i][j] = 2.0 * r[i][j];
}

/* v = M(q)^{-1} p, body by body (M_e^{-1} in closed form, module notes). */
static void velocity(long N, const double *q, const double *p, double *v) {
    for (long k = 0; k < N; k++) {
        const double *e = q + 7 * k + 3, *pk = p + 7 * k;
        double a[4], n2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3];
        for (int i = 0; i < 3; i++) v[7 * k + i] = pk[i] / MASS;
        a_times(e, pk + 3, a);
        for (int i = 0; i < 4; i++) a[i] *= Dinv[i];
        at_times(e, a, 0.25 / (n2 * n2), v + 7 * k + 3);
    }
}

/* F = -grad U + dT/dq(q, v). */
static void force(long N, const double *q, const double *v, double *F) {
    for (long k = 0; k < N; k++) {
        const double *e = q + 7 * k + 3, *ed = v + 7 * k + 3;
        double a[4], Ja[4];
        F[7 * k] = 0.0;
        F[7 * k + 1] = 0.0;
        F[7 * k + 2] = -MASS * GRAVITY;
        a_times(e, ed, a);
        /* dT/de = 4 (j0 a_0 e' - E(e')^T J a_{1:3}) = 4 A(e')^T (j0 a_0, -J a_{1:3}). */
        Ja[0] = D[0] * a[0];
        for (int i = 1; i < 4; i++) Ja[i] = -D[i] * a[i];
        at_times(ed, Ja, 4.0, F + 7 * k + 3);
    }
}

/* out = G(q)^T lam: body k takes its own rows (lam_k) and the joint rows of body k+1. */
static void gt_times(long N, double l, const double *q, const double *lam, double *out) {
    for (long k = 0; k < N; k++) {
        const double *e = q + 7 * k + 3, *lk = lam + 4 * k;
        const double *ln = k + 1 < N ? lam + 4 * k + 4 : NULL;
        double C[3][4], s[3];
        axis_jacobian(e, C);
        for (int i = 0; i < 3; i++) {
            out[7 * k + i] = ln ? lk[1 + i] - ln[1 + i] : lk[1 + i];
            s[i] = ln ? lk[1 + i] + ln[1 + i] : lk[1 + i];
        }
        for (int j = 0; j < 4; j++)
            out[7 * k + 3 + j] = 2.0 * e[j] * lk[0] + l * (C[0][j] * s[0] + C[1][j] * s[1]
                                                           + C[2][j] * s[2]);
    }
}

/* out = G(q) v: e . e' terms and the velocity of upper point k less that of lower point
 * k-1. */
static void g_times(long N, double l, const double *q, const double *v, double *out) {
    double below[3] = {0.0, 0.0, 0.0}; /* velocity of the lower point above (fixed at 0) */
    for (long k = 0; k < N; k++) {
        const double *e = q + 7 * k + 3, *vx = v + 7 * k, *ed = v + 7 * k + 3;
        double C[3][4];
        axis_jacobian(e, C);
        out[4 * k] = 2.0 * (e[0] * ed[0] + e[1] * ed[1] + e[2] * ed[2] + e[3] * ed[3]);
        for (int i = 0; i < 3; i++) {
            const double turn = l * (C[i][0] * ed[0] + C[i][1] * ed[1] + C[i][2] * ed[2]
                                     + C[i][3] * ed[3]);
            out[4 * k + 1 + i] = vx[i] + turn - below[i];
            below[i] = vx[i] - turn;
        }
    }
}

/* out = g(q), in the module's order and arithmetic (upper - lower point above). */
static void constraints(long N, double l, const double *q, double *out) {
    double above[3] = {0.0, 0.0, 0.0};
    for (long k = 0; k < N; k++) {
        const double *x = q + 7 * k, *e = q + 7 * k + 3;
        double c[3];
        axis(e, c);
        out[4 * k] = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] - 1.0;
        for (int i = 0; i < 3; i++) {
            out[4 * k + 1 + i] = (x[i] + l * c[i]) - above[i];
            above[i] = x[i] - l * c[i];
        }
    }
}

/* Block Cholesky of S(q) = G M^{-1} G^T: Ld[k] = L_kk (lower triangle; the upper one is
 * never read), Ls[k] = L_{k,k-1} (row 0 zero), 4 x 4 row-major. Ld holds the reciprocals
 * of L_kk's diagonal on its diagonal, so that the solves multiply rather than divide.
 * Returns 0 where a pivot is not positive (S numerically singular). */
static int schur_factor(long N, double l, const double *q, double *Ld, double *Ls) {
    double prev[4][4] = {{0}}; /* Q_{k-1} */
    for (long k = 0; k < N; k++) {
        const double *e = q + 7 * k + 3;
        double C[3][4], B[4][4], AB[4][4], Q[4][4], S[4][4];
        const double n2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3];
        const double scale = 0.25 / (n2 * n2);
        double *L = Ld + 16 * k, *Lsub = Ls + 16 * k;
        /* Q = B^T M_e^{-1} B + (0 on row/column 0, I3 / m_b), B's columns the e parts of
         * body k's rows (2e, l C^T); M_e^{-1} = A^T D^{-1} A / (4|e|^4) makes it a weighted
         * Gram matrix of the columns of A B. */
        axis_jacobian(e, C);
        for (int j = 0; j < 4; j++) {
            B[0][j] = 2.0 * e[j];
            for (int i = 0; i < 3; i++) B[1 + i][j] = l * C[i][j];
        }
        for (int c = 0; c < 4; c++) a_times(e, B[c], AB[c]); /* AB[c] = A b_c */
        for (int i = 0; i < 4; i++)
            for (int j = 0; j <= i; j++) {
                double s = 0.0;
                for (int r = 0; r < 4; r++) s += AB[i][r] * AB[j][r] * Dinv[r];
                Q[i][j] = Q[j][i] = s * scale + (i == j && i > 0 ? 1.0 / MASS : 0.0);
            }
        memcpy(S, Q, sizeof S);
        memset(Lsub, 0, 16 * sizeof *Lsub);
        if (k > 0) {
            const double *Lp = Ld + 16 * (k - 1);
            for (int i = 1; i < 4; i++) {
                for (int j = 1; j < 4; j++) S[i][j] += prev[i][j];
                /* Row i of L_{k,k-1}: L_{k-1,k-1} x = row i of S_{k,k-1}. */
                for (int j = 0; j < 4; j++) {
                    double s = prev[i][j] - (j == i ? 2.0 / MASS : 0.0);
                    for (int c = 0; c < j; c++) s -= Lp[4 * j + c] * Lsub[4 * i + c];
                    Lsub[4 * i + j] = s * Lp[4 * j + j];
                }
            }
            for (int i = 1; i < 4; i++)
                for (int j = 1; j <= i; j++)
                    for (int c = 0; c < 4; c++) S[i][j] -= Lsub[4 * i + c] * Lsub[4 * j + c];
        }
        for (int j = 0; j < 4; j++) {
            double d = S[j][j];
            for (int c = 0; c < j; c++) d -= L[4 * j + c] * L[4 * j + c];
            if (!(d > 0.0) || !isfinite(d)) return 0;
            L[4 * j + j] = 1.0 / sqrt(d);
            for (int i = j + 1; i < 4; i++) {
                double s = S[i][j];
                for (int c = 0; c < j; c++) s -= L[4 * i + c] * L[4 * j + c];
                L[4 * i + j] = s * L[4 * j + j];
            }
        }
        memcpy(prev, Q, sizeof prev);
    }
    return 1;
}

/* Solve S x = b in place (x holds b) with the factor of schur_factor, then scale by s. */
static void schur_solve(long N, const double *Ld, const double *Ls, double *x, double s) {
    for (long k = 0; k < N; k++) { /* forward: L_kk y_k = b_k - L_{k,k-1} y_{k-1} */
        const double *L = Ld + 16 * k, *Lsub = Ls + 16 * k;
        double *y = x + 4 * k;
        for (int i = 0; i < 4; i++) {
            double t = y[i];
            if (k > 0 && i > 0) /* row 0 of L_{k,k-1} is zero */
                for (int c = 0; c < 4; c++) t -= Lsub[4 * i + c] * x[4 * (k - 1) + c];
            for (int c = 0; c < i; c++) t -= L[4 * i + c] * y[c];
            y[i] = t * L[4 * i + i];
        }
    }
    for (long k = N - 1; k >= 0; k--) { /* backward: L_kk^T x_k = y_k - L_{k+1,k}^T x_{k+1} */
        const double *L = Ld + 16 * k;
        double *y = x + 4 * k;
        for (int i = 3; i >= 0; i--) {
            double t = y[i];
            if (k + 1 < N)
                for (int r = 1; r < 4; r++) t -= Ls[16 * (k + 1) + 4 * r + i] * y[4 + r];
            for (int r = i + 1; r < 4; r++) t -= L[4 * r + i] * y[r];
            y[i] = t * L[4 * i + i];
        }
    }
    for (long i = 0; i < 4 * N; i++) x[i] *= s;
}

/* H = T(q, v) + U(q) in velocity form, as the suite measures it. */
static double energy(long N, const double *q, const double *v) {
    double T = 0.0, U = 0.0;
    for (long k = 0; k < N; k++) {
        const double *vx = v + 7 * k;
        double a[4];
        a_times(q + 7 * k + 3, v + 7 * k + 3, a);
        T += 0.5 * MASS * (vx[0] * vx[0] + vx[1] * vx[1] + vx[2] * vx[2])
             + 2.0 * (D[0] * a[0] * a[0] + D[1] * a[1] * a[1] + D[2] * a[2] * a[2]
                      + D[3] * a[3] * a[3]);
        U += q[7 * k + 2];
    }
    return T + MASS * GRAVITY * U;
}

static double max_abs(size_t len, const double *x) {
    double m = 0.0;
    /* A comparison, not fmax: the library call was a quarter of the run time at -O2. */
    for (size_t i = 0; i < len; i++)
        if (fabs(x[i]) > m) m = fabs(x[i]);
    return m;
}

/* Newton's residual r = (r1, r2, r3) at z = (p_half, q1, lam) (module notes); leaves
 * v0 = M(q0)^{-1} p_half and v1 = M(q1)^{-1} p_half, the latter for the velocity projection.
 * Returns max|r|, NaN where r has one, so that a non-finite residual stops Newton. */
static double residual(long N, double l, double h, const double *q0, const double *p0,
                       const double *z, double *r, double *v0, double *v1, double *f) {
    const size_t n = 7 * (size_t)N;
    const double *ph = z, *q1 = z + n, *lam = z + 2 * n;
    double *r1 = r, *r2 = r + n, *r3 = r + 2 * n, big = 0.0;
    velocity(N, q0, ph, v0);
    force(N, q0, v0, f);
    gt_times(N, l, q0, lam, r1);
    velocity(N, q1, ph, v1);
    for (size_t i = 0; i < n; i++) {
        r1[i] = ph[i] - p0[i] - 0.5 * h * (f[i] - r1[i]);
        r2[i] = q1[i] - q0[i] - 0.5 * h * (v0[i] + v1[i]);
    }
    constraints(N, l, q1, r3);
    int nan = 0;
    for (size_t i = 0; i < 2 * n + 4 * (size_t)N; i++) {
        const double a = fabs(r[i]);
        nan |= isnan(a);
        if (a > big) big = a;
    }
    return nan ? NAN : big;
}

/* Quaternion product c = a b (scalar first). */
static void quat_mul(const double *a, const double *b, double *c) {
    c[0] = a[0] * b[0] - (a[1] * b[1] + a[2] * b[2] + a[3] * b[3]);
    c[1] = a[0] * b[1] + b[0] * a[1] + (a[2] * b[3] - a[3] * b[2]);
    c[2] = a[0] * b[2] + b[0] * a[2] + (a[3] * b[1] - a[1] * b[3]);
    c[3] = a[0] * b[3] + b[0] * a[3] + (a[1] * b[2] - a[2] * b[1]);
}

static void cross(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

/* problems/rigid_chain.py initial_state: attitudes q_z(phi_k) q_x(theta0) q_z(psi_k), the
 * positions and velocities following down the chain from the fixed point. */
static void initial_state(long N, double l, double *q, double *v) {
    double w[3] = {0.0, 0.0, 0.0}, wd[3] = {0.0, 0.0, 0.0};
    for (long k = 0; k < N; k++) {
        const double qz[4] = {cos(PHI_STEP * k / 2), 0.0, 0.0, sin(PHI_STEP * k / 2)};
        const double qx[4] = {cos(THETA0 / 2), sin(THETA0 / 2), 0.0, 0.0};
        const double qp[4] = {cos(PSI_STEP * k / 2), 0.0, 0.0, sin(PSI_STEP * k / 2)};
        double t[4], *x = q + 7 * k, *e = q + 7 * k + 3, *xd = v + 7 * k, *ed = v + 7 * k + 3;
        double c[3], om[4], rel[3], turn[3];
        quat_mul(qz, qx, t);
        quat_mul(t, qp, e);
        const double norm = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3]);
        for (int i = 0; i < 4; i++) e[i] /= norm;
        axis(e, c);
        om[0] = 0.0; /* (0, Omega_k), Omega_k = precession e_z + spin R_k e_z */
        for (int i = 0; i < 3; i++) om[1 + i] = (i == 2 ? PRECESSION : 0.0) + SPIN * c[i];
        for (int i = 0; i < 3; i++) {
            x[i] = w[i] - l * c[i];
            rel[i] = x[i] - w[i];
        }
        cross(om + 1, rel, turn);
        for (int i = 0; i < 3; i++) xd[i] = wd[i] + turn[i];
        quat_mul(om, e, t);
        for (int i = 0; i < 4; i++) ed[i] = 0.5 * t[i];
        for (int i = 0; i < 3; i++) {
            w[i] = x[i] - l * c[i];
            rel[i] = w[i] - x[i];
        }
        cross(om + 1, rel, turn);
        for (int i = 0; i < 3; i++) wd[i] = xd[i] + turn[i];
    }
}

int main(int argc, char **argv) {
    long N, n_steps;
    double h, tol;
    int print_state;
    if (parse_arguments(argc, argv, "N_BODIES", &N, &n_steps, &h, &tol, &print_state))
        return 2;
    D[0] = (J[0] + J[1] + J[2]) / 3.0;
    for (int i = 0; i < 3; i++) D[1 + i] = J[i];
    for (int i = 0; i < 4; i++) Dinv[i] = 1.0 / D[i];
    const double l = HALF_LENGTH;
    const size_t n = 7 * (size_t)N, m = 4 * (size_t)N, nz = 2 * n + m;
    double *q = malloc(n * sizeof *q), *p = malloc(n * sizeof *p), *v = malloc(n * sizeof *v);
    double *z = malloc(nz * sizeof *z), *r = malloc(nz * sizeof *r), *dz = malloc(nz * sizeof *dz);
    double *v0 = malloc(n * sizeof *v0), *v1 = malloc(n * sizeof *v1), *f = malloc(n * sizeof *f);
    double *t = malloc(n * sizeof *t), *mu = calloc(m, sizeof *mu);
    double *L0 = malloc(16 * N * sizeof *L0), *Ls0 = malloc(16 * N * sizeof *Ls0);
    double *L1 = malloc(16 * N * sizeof *L1), *Ls1 = malloc(16 * N * sizeof *Ls1);
    const long n_win = n_steps < MAX_WINDOWS ? n_steps : MAX_WINDOWS;
    double(*win)[3] = calloc(n_win, sizeof *win);
    if (!q || !p || !v || !z || !r || !dz || !v0 || !v1 || !f || !t || !mu || !L0 || !Ls0
        || !L1 || !Ls1 || !win) {
        fprintf(stderr, "out of memory for N = %ld\n", N);
        return 1;
    }
    initial_state(N, l, q, v);
    /* p0 = M(q0) v0, body by body (M_e = 4 A^T D A). */
    for (long k = 0; k < N; k++) {
        double a[4];
        for (int i = 0; i < 3; i++) p[7 * k + i] = MASS * v[7 * k + i];
        a_times(q + 7 * k + 3, v + 7 * k + 3, a);
        for (int i = 0; i < 4; i++) a[i] *= D[i];
        at_times(q + 7 * k + 3, a, 4.0, p + 7 * k + 3);
    }
    velocity(N, q, p, v);
    const double H0 = energy(N, q, v);
    if (!schur_factor(N, l, q, L0, Ls0)) {
        fprintf(stderr, "G M^-1 G^T is singular at the start\n");
        return 1;
    }
    double *ph = z, *q1 = z + n, *lam = z + 2 * n;
    long iterations = 0;

    struct timespec w0, w1, c0, c1;
    clock_gettime(CLOCK_MONOTONIC, &w0);
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &c0);
    for (long step = 0; step < n_steps; step++) {
        /* Position projection: simplified Newton from z0 = (p0, q0 + h M0^{-1} p0, mu);
         * v = M0^{-1} p0 is left by the previous step's bookkeeping (or the set-up). */
        for (size_t i = 0; i < n; i++) {
            ph[i] = p[i];
            q1[i] = q[i] + h * v[i];
        }
        memcpy(lam, mu, m * sizeof *lam);
        double rn = residual(N, l, h, q, p, z, r, v0, v1, f);
        int done = rn <= tol, it = 0;
        int go = !done && isfinite(rn);
        while (go) {
            /* Correction with the Jacobian frozen at q0 (module notes). */
            double *r1 = r, *r2 = r + n, *r3 = r + 2 * n;
            double *dp = dz, *dq = dz + n, *dlam = dz + 2 * n;
            velocity(N, q, r1, t);
            for (size_t i = 0; i < n; i++) t[i] = r2[i] + h * t[i];
            g_times(N, l, q, t, dlam);
            for (size_t i = 0; i < m; i++) dlam[i] = r3[i] - dlam[i];
            schur_solve(N, L0, Ls0, dlam, 2.0 / (h * h));
            gt_times(N, l, q, dlam, dp);
            for (size_t i = 0; i < n; i++) dp[i] = -r1[i] - 0.5 * h * dp[i];
            velocity(N, q, dp, dq);
            for (size_t i = 0; i < n; i++) dq[i] = -r2[i] + h * dq[i];
            /* rattle's bound on the residual's terms: |z| before the correction. */
            const double terms = max_abs(nz, z);
            for (size_t i = 0; i < nz; i++) z[i] += dz[i];
            const double rn_new = residual(N, l, h, q, p, z, r, v0, v1, f);
            it++;
            const double dz_norm = max_abs(nz, dz), floor_r = EPS * (1.0 + terms);
            /* Halving counts only above the floor once within the window (newton.py). */
            const int halved = rn_new <= 0.5 * rn
                && !(rn_new <= floor_r && rn <= SIMPLIFIED_WINDOW * floor_r);
            const int stalled = !halved && rn_new <= SIMPLIFIED_WINDOW * floor_r;
            done = rn_new <= tol || dz_norm <= 4.0 * EPS * (1.0 + max_abs(nz, z)) || stalled;
            /* Simplified Newton goes on only while it halves the residual. */
            go = !done && it < MAX_ITER && isfinite(rn_new) && rn_new <= 0.5 * rn;
            rn = rn_new;
        }
        iterations += it;
        int finite = 1;
        for (size_t i = 0; i < nz; i++) finite &= isfinite(z[i]) != 0;
        if (!done || !finite) {
            fprintf(stderr, "simplified Newton did not converge at step %ld (residual %.3e, "
                            "%d iterations); rattle would go on with the exact Jacobian\n",
                    step + 1, rn, it);
            return 1;
        }
        /* Velocity projection at q1: base = p_half + h/2 F(q1, p_half), v1 = M1^{-1} p_half
         * from the last residual. */
        force(N, q1, v1, f);
        for (size_t i = 0; i < n; i++) p[i] = ph[i] + 0.5 * h * f[i];
        velocity(N, q1, p, t);
        g_times(N, l, q1, t, mu);
        if (!schur_factor(N, l, q1, L1, Ls1)) {
            fprintf(stderr, "G M^-1 G^T is singular at step %ld\n", step + 1);
            return 1;
        }
        schur_solve(N, L1, Ls1, mu, 2.0 / h);
        gt_times(N, l, q1, mu, f);
        for (size_t i = 0; i < n; i++) {
            p[i] -= 0.5 * h * f[i];
            q[i] = q1[i];
        }
        /* S1 is the next step's S0 (first same as last). */
        double *swap_d = L0, *swap_s = Ls0;
        L0 = L1, Ls0 = Ls1, L1 = swap_d, Ls1 = swap_s;
        /* Bookkeeping: |g|, |G v| and |H - H0| at the step's end. */
        velocity(N, q, p, v);
        constraints(N, l, q, dz);
        const double g_norm = max_abs(m, dz);
        g_times(N, l, q, v, dz);
        const double mx[3] = {g_norm, max_abs(m, dz), fabs(energy(N, q, v) - H0)};
        double *row = win[step * n_win / n_steps];
        for (int j = 0; j < 3; j++) row[j] = fmax(row[j], mx[j]);
    }
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &c1);
    clock_gettime(CLOCK_MONOTONIC, &w1);
    double mx[3] = {0.0, 0.0, 0.0};
    for (long i = 0; i < n_win; i++)
        for (int j = 0; j < 3; j++) mx[j] = fmax(mx[j], win[i][j]);
    const double secs = (w1.tv_sec - w0.tv_sec) + 1e-9 * (w1.tv_nsec - w0.tv_nsec);
    const double cpu = (c1.tv_sec - c0.tv_sec) + 1e-9 * (c1.tv_nsec - c0.tv_nsec);
    printf("%ld %.9f %.9f %.17g %.17g %.17g %ld %ld\n", n_steps, secs, cpu, mx[0], mx[1], mx[2],
           iterations, peak_rss_kib());
    if (print_state) { /* v = M(q)^{-1} p from the last bookkeeping */
        for (size_t i = 0; i < n; i++) printf("%.17g%c", q[i], i + 1 < n ? ' ' : '\n');
        for (size_t i = 0; i < n; i++) printf("%.17g%c", v[i], i + 1 < n ? ' ' : '\n');
    }
    return 0;
}
