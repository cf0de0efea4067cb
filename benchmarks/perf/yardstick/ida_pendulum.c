/* IDA on the pendulum (IFToMM A01, L = m = 1, g0 = 9.81) with hand-written C residuals and
 * iteration matrices: the native cost of `ida-ggl` and `ida-index1`.
 *
 * The residuals are those of integrators/ida.py, written out by hand, y = (x, y, u, w, lam
 * [, mu]):
 *   GGL:     x' - u + 2 x mu,  y' - w + 2 y mu,  u' + 2 x lam,  w' + g0 + 2 y lam,
 *            x^2 + y^2 - 1,  2 (x u + y w);
 *   index 1: x' - u,  y' - w,  u' + 2 x lam,  w' + g0 + 2 y lam,
 *            2 (x u' + y w') + 2 (u^2 + w^2).
 * IDA is set up by the same driver as the suite's native path (integrators/sundials.c,
 * included below), so the settings are the suite's by construction and the difference in
 * time per step is what the suite adds: generated code, the drift record, Python.
 *
 * usage: ida_pendulum ggl|index1 RTOL ATOL T_END ROUNDS Y0... YP0...
 * (the initial values, n = 6 or 5 each: the suite's consistent_values, so that both start
 * from the same point)
 * prints: steps, residual calls, Jacobians, the best of ROUNDS solve times (s), final y.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define G0 9.81
static int ggl = 1;

static void res(double t, const double *y, const double *yp, double *r)
{
    const double x = y[0], z = y[1], u = y[2], w = y[3], lam = y[4];
    const double mu = ggl ? y[5] : 0.0;
    r[0] = yp[0] - u + 2.0 * x * mu;
    r[1] = yp[1] - w + 2.0 * z * mu;
    r[2] = yp[2] + 2.0 * x * lam;
    r[3] = yp[3] + G0 + 2.0 * z * lam;
    if (ggl) {
        r[4] = x * x + z * z - 1.0;
        r[5] = 2.0 * (x * u + z * w);
    } else {
        r[4] = 2.0 * (x * yp[2] + z * yp[3]) + 2.0 * (u * u + w * w);
    }
}

/* dF/dy + cj dF/dy', column-major. */
static void jac(double t, const double *y, const double *yp, double cj, double *J)
{
    const int n = ggl ? 6 : 5;
    const double x = y[0], z = y[1], u = y[2], w = y[3], lam = y[4];
    memset(J, 0, sizeof(double) * n * n);
#define A(i, j) J[(i) + (j) * n]
    for (int i = 0; i < 4; i++) A(i, i) = cj;
    A(0, 2) = -1.0;
    A(1, 3) = -1.0;
    A(2, 0) = 2.0 * lam;
    A(3, 1) = 2.0 * lam;
    A(2, 4) = 2.0 * x;
    A(3, 4) = 2.0 * z;
    if (ggl) {
        const double mu = y[5];
        A(0, 0) += 2.0 * mu;
        A(1, 1) += 2.0 * mu;
        A(0, 5) = 2.0 * x;
        A(1, 5) = 2.0 * z;
        A(4, 0) = 2.0 * x;
        A(4, 1) = 2.0 * z;
        A(5, 0) = 2.0 * u;
        A(5, 1) = 2.0 * w;
        A(5, 2) = 2.0 * x;
        A(5, 3) = 2.0 * z;
    } else {
        A(4, 0) = 2.0 * yp[2];
        A(4, 1) = 2.0 * yp[3];
        A(4, 2) = 4.0 * u + 2.0 * cj * x;
        A(4, 3) = 4.0 * w + 2.0 * cj * z;
    }
#undef A
}

#include "sundials.c"

static double seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

int main(int argc, char **argv)
{
    ggl = argc > 1 && strcmp(argv[1], "ggl") == 0;
    const int n = ggl ? 6 : 5;
    if (argc != 6 + 2 * n || (!ggl && strcmp(argv[1], "index1"))) {
        fprintf(stderr, "usage: %s ggl|index1 RTOL ATOL T_END ROUNDS Y0... YP0...\n", argv[0]);
        return 2;
    }
    const double rtol = atof(argv[2]), atol = atof(argv[3]), t_end = atof(argv[4]);
    const int rounds = atoi(argv[5]);
    double y0[6], yp0[6], atols[6], id[6];
    for (int i = 0; i < n; i++) {
        y0[i] = atof(argv[6 + i]);
        yp0[i] = atof(argv[6 + n + i]);
        atols[i] = i < 4 ? atol : 1e30;
        id[i] = i < 4 ? 1.0 : 0.0;
    }
    double best = INFINITY, t = 0.0, buf_t[1];
    double buf_y[6], y[6];
    long steps = 0, counts[4] = {0};
    for (int r = 0; r < rounds; r++) {
        int flag;
        const double start = seconds();
        Solver *s = solver_new(n, 0.0, y0, yp0, rtol, atols, id, 1, 5, 5000000, 4, 10, 0.0,
                               0.0, 0.0, t_end, &flag);
        if (!s) {
            fprintf(stderr, "IDA did not initialise (flag %d)\n", flag);
            return 1;
        }
        steps = 0;
        t = 0.0;
        while (t < t_end) {
            steps += solver_steps(s, t_end, 1, buf_t, buf_y, &flag, &t);
            if (flag < 0) {
                fprintf(stderr, "IDA failed at t = %g: %s\n", t, s->message);
                return 1;
            }
        }
        const double elapsed = seconds() - start;
        if (elapsed < best) best = elapsed;
        solver_counts(s, counts);
        solver_state(s, y);
        solver_free(s);
    }
    printf("steps %ld\ncalls %ld\njacobians %ld\nseconds %.9g\ny", steps, counts[0], counts[3],
           best);
    for (int i = 0; i < n; i++) printf(" %.17g", y[i]);
    printf("\n");
    return 0;
}
