/* SUNDIALS IDA on a mechanical system's GGL or index-1 form, called from C: the native cost
 * of `ida-ggl` and `ida-index1`.
 *
 * The system comes in a header, dae_model.h, that the efficiency benchmark generates from
 * the problem's own JAX functions (linalg/codegen.py) as the suite's native driver
 * generates them (integrators/sundials.py): NEQ unknowns y (q, v and the multipliers; the
 * first NQV are q and v), the residual `res` of integrators/ida.py's formulation and its
 * autodiff iteration matrix `jac`. IDA is set up by the same driver as the suite's native
 * path (integrators/sundials.c, included below), so the settings are the suite's by
 * construction and the difference in time per step is what the suite adds: the drift
 * record, Python between chunks of steps.
 *
 * usage: ida RTOL ATOL MULTIPLIER_ATOL MAX_ORDER MAX_NONLIN_ITERS MAX_CONV_FAILS FIRST_STEP
 *        MIN_STEP MAX_STEP T0 T_END ROUNDS Y0(NEQ) YP0(NEQ)
 * (the initial values: the suite's consistent_values, so that both start from the same
 * point)
 * prints: steps, residual calls, Jacobians, the best of ROUNDS solve times (wall and
 * processor, s), final y.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "common.h"

#include "dae_model.h"
#include "sundials.c"

#define N_ARGS (12 + 2 * NEQ)

int main(int argc, char **argv)
{
    if (argc != 1 + N_ARGS) {
        fprintf(stderr, "usage: %s RTOL ATOL MULTIPLIER_ATOL MAX_ORDER MAX_NONLIN_ITERS "
                        "MAX_CONV_FAILS FIRST_STEP MIN_STEP MAX_STEP T0 T_END ROUNDS Y0(%d) "
                        "YP0(%d)\n", argv[0], NEQ, NEQ);
        return 2;
    }
    double v[N_ARGS];
    if (parse_numbers(argv, N_ARGS, v)) return 2;
    const double rtol = v[0], atol = v[1], matol = v[2];
    const int max_order = (int)v[3], max_nonlin = (int)v[4], max_fails = (int)v[5];
    const double first_step = v[6], min_step = v[7], max_step = v[8], t0 = v[9];
    const double t_end = v[10];
    const int rounds = (int)v[11];
    const double *y0 = v + 12, *yp0 = v + 12 + NEQ;
    if (!(rtol > 0 && atol > 0 && matol > 0 && rounds >= 1 && t_end > t0)) {
        fprintf(stderr, "%s: need RTOL, ATOL, MULTIPLIER_ATOL > 0, T_END > T0, ROUNDS >= 1\n",
                argv[0]);
        return 2;
    }
    double atols[NEQ], id[NEQ], y[NEQ], buf_t[1], buf_y[NEQ];
    for (int i = 0; i < NEQ; i++) {
        atols[i] = i < NQV ? atol : matol;
        id[i] = i < NQV ? 1.0 : 0.0;
    }
    double best = INFINITY, best_cpu = INFINITY;
    long steps = 0, counts[4] = {0};
    for (int r = 0; r < rounds; r++) {
        int flag;
        const double start = seconds_of(CLOCK_MONOTONIC);
        const double cpu = seconds_of(CLOCK_PROCESS_CPUTIME_ID);
        Solver *s = solver_new(NEQ, t0, y0, yp0, rtol, atols, id, 1, max_order, 5000000,
                               max_nonlin, max_fails, first_step, min_step, max_step, t_end,
                               &flag);
        if (!s) {
            fprintf(stderr, "IDA did not initialise (flag %d)\n", flag);
            return 1;
        }
        double t = t0;
        steps = 0;
        while (t < t_end) {
            steps += solver_steps(s, t_end, 1, buf_t, buf_y, &flag, &t);
            if (flag < 0) {
                fprintf(stderr, "IDA failed at t = %g: %s\n", t, s->message);
                return 1;
            }
        }
        best = fmin(best, seconds_of(CLOCK_MONOTONIC) - start);
        best_cpu = fmin(best_cpu, seconds_of(CLOCK_PROCESS_CPUTIME_ID) - cpu);
        solver_counts(s, counts);
        solver_state(s, y);
        solver_free(s);
    }
    printf("steps %ld\ncalls %ld\njacobians %ld\nseconds %.9g\ncpu_seconds %.9g\ny", steps,
           counts[0], counts[3], best, best_cpu);
    for (int i = 0; i < NEQ; i++) printf(" %.17g", y[i]);
    printf("\n");
    return 0;
}
