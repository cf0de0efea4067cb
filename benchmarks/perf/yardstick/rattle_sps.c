/* Speed-of-light yardstick: RATTLE on the reduced SPS receiver in plain C.
 *
 * The same step as integrators/rattle.py takes for a separable Hamiltonian: a Newton
 * iteration on the position multiplier with the same residual test, the linear velocity
 * projection, and the same per-step bookkeeping (|g|, |G v|, |H - H0| and their
 * per-window maxima), so the ratio of step rates compares like with like.
 *
 * usage: rattle_sps N_STEPS H [NEWTON_TOL]  (tolerance default 1e-16, as rattle's)
 *     -> prints "steps seconds R r vR vr max_g max_gv max_dH newton_iterations cpu_seconds"
 * (seconds: wall clock of the loop; cpu_seconds: this process's CPU time in the loop).
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#define NWIN 1000

static const double Mo = 0.8, mi = 1.0, w = 1.0;

static double constraint(const double *q, double c, double l2) {
    return q[0] * q[0] + q[1] * q[1] - 2.0 * c * q[0] * q[1] - l2;
}

int main(int argc, char **argv) {
    if (argc != 3 && argc != 4) {
        fprintf(stderr, "usage: %s N_STEPS H [NEWTON_TOL]\n", argv[0]);
        return 2;
    }
    const long n = atol(argv[1]);
    const double h = atof(argv[2]);
    const double c = cos(M_PI / 6.0), eps = 2.220446049250313e-16;
    const double tol = argc == 4 ? atof(argv[3]) : 1e-16;
    long iterations = 0;
    const double mass[2] = {6.0 * Mo, 6.0 * mi};
    double q[2] = {1.0, 0.8}, p[2] = {0.0, 0.0}, lam = 0.0;
    const double l2 = q[0] * q[0] + q[1] * q[1] - 2.0 * c * q[0] * q[1];
    /* F = -grad U with U = -3 w^2 (M R^2 + m r^2) */
    double F[2] = {6.0 * w * w * Mo * q[0], 6.0 * w * w * mi * q[1]};
    const double H0 = -3.0 * w * w * (Mo * q[0] * q[0] + mi * q[1] * q[1]);
    static double win[NWIN][3];
    struct timespec t0, t1, c0, c1;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &c0);
    for (long k = 0; k < n; k++) {
        const double G0[2] = {2.0 * (q[0] - c * q[1]), 2.0 * (q[1] - c * q[0])};
        double ph[2], q1[2], r, rprev = INFINITY, dl = INFINITY;
        int it = 0;
        for (;;) {
            ph[0] = p[0] + 0.5 * h * (F[0] - G0[0] * lam);
            ph[1] = p[1] + 0.5 * h * (F[1] - G0[1] * lam);
            q1[0] = q[0] + h * ph[0] / mass[0];
            q1[1] = q[1] + h * ph[1] / mass[1];
            r = constraint(q1, c, l2);
            const double floor_r = fmax(tol, eps * (1 + fabs(lam)));
            int stalled = fabs(r) > 0.5 * rprev && fabs(r) <= 1e3 * floor_r;
            int at_floor = fabs(r) <= 2 * floor_r && fabs(r) <= 1e-2 * rprev && isfinite(rprev);
            if (fabs(r) <= tol || fabs(dl) <= 4 * eps * (1 + fabs(lam)) || at_floor || stalled)
                break;
            if (++it > 20) {
                fprintf(stderr, "Newton failed at step %ld\n", k + 1);
                return 1;
            }
            const double G1[2] = {2.0 * (q1[0] - c * q1[1]), 2.0 * (q1[1] - c * q1[0])};
            const double J = -0.5 * h * h * (G1[0] * G0[0] / mass[0] + G1[1] * G0[1] / mass[1]);
            dl = -r / J;
            lam += dl;
            iterations++;
            rprev = fabs(r);
        }
        const double G1[2] = {2.0 * (q1[0] - c * q1[1]), 2.0 * (q1[1] - c * q1[0])};
        F[0] = 6.0 * w * w * Mo * q1[0];
        F[1] = 6.0 * w * w * mi * q1[1];
        const double b[2] = {ph[0] + 0.5 * h * F[0], ph[1] + 0.5 * h * F[1]};
        const double S = 0.5 * h * (G1[0] * G1[0] / mass[0] + G1[1] * G1[1] / mass[1]);
        const double mu = (G1[0] * b[0] / mass[0] + G1[1] * b[1] / mass[1]) / S;
        p[0] = b[0] - 0.5 * h * G1[0] * mu;
        p[1] = b[1] - 0.5 * h * G1[1] * mu;
        q[0] = q1[0];
        q[1] = q1[1];
        const double v[2] = {p[0] / mass[0], p[1] / mass[1]};
        const double Gq[2] = {2.0 * (q[0] - c * q[1]), 2.0 * (q[1] - c * q[0])};
        const double m[3] = {
            fabs(constraint(q, c, l2)),
            fabs(Gq[0] * v[0] + Gq[1] * v[1]),
            fabs(0.5 * (mass[0] * v[0] * v[0] + mass[1] * v[1] * v[1])
                 - 3.0 * w * w * (Mo * q[0] * q[0] + mi * q[1] * q[1]) - H0)};
        double *row = win[k * NWIN / n];
        for (int j = 0; j < 3; j++) row[j] = m[j] > row[j] ? m[j] : row[j];
    }
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &c1);
    clock_gettime(CLOCK_MONOTONIC, &t1);
    double mx[3] = {0, 0, 0};
    for (int i = 0; i < NWIN; i++)
        for (int j = 0; j < 3; j++) mx[j] = win[i][j] > mx[j] ? win[i][j] : mx[j];
    const double secs = (t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec);
    const double cpu = (c1.tv_sec - c0.tv_sec) + 1e-9 * (c1.tv_nsec - c0.tv_nsec);
    printf("%ld %.9f %.17g %.17g %.17g %.17g %.3e %.3e %.3e %ld %.9f\n", n, secs, q[0], q[1],
           p[0] / mass[0], p[1] / mass[1], mx[0], mx[1], mx[2], iterations, cpu);
    return 0;
}
