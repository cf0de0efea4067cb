/* What the O(N) C yardsticks share: their command line and their peak-memory reading.
 *
 * usage: PROGRAM N N_STEPS H [NEWTON_TOL [state]]  (tolerance default 1e-16, as rattle's;
 * "state" also prints the final q and v). Included by rattle_chain.c and
 * rattle_rigid_chain.c, each compiled on its own (benchmarks/perf/processes.py).
 */
#ifndef YARDSTICK_H
#define YARDSTICK_H

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Peak resident set of this program (KiB), -1 where /proc does not give it. Not getrusage:
 * Linux charges a program with the resident set of the process that started it. */
static long peak_rss_kib(void) {
    FILE *f = fopen("/proc/self/status", "r");
    char line[256];
    long kib = -1;
    if (!f) return -1;
    while (fgets(line, sizeof line, f))
        if (sscanf(line, "VmHWM: %ld kB", &kib) == 1) break;
    fclose(f);
    return kib;
}

static int positive_long(const char *s, long *out) {
    char *end;
    *out = strtol(s, &end, 10);
    return *s != '\0' && *end == '\0' && *out >= 1;
}

static int positive_double(const char *s, double *out) {
    char *end;
    *out = strtod(s, &end);
    return *s != '\0' && *end == '\0' && isfinite(*out) && *out > 0.0;
}

/* Read the command line above into its arguments (what = the name of N in the usage line).
 * Returns 0, or 2 after a usage line on stderr. */
static int parse_arguments(int argc, char **argv, const char *what, long *N, long *n_steps,
                           double *h, double *tol, int *print_state) {
    *tol = 1e-16;
    *print_state = argc == 6 && strcmp(argv[5], "state") == 0;
    if (argc < 4 || argc > 6 || (argc == 6 && !*print_state) || !positive_long(argv[1], N)
        || !positive_long(argv[2], n_steps) || !positive_double(argv[3], h)
        || (argc >= 5 && !positive_double(argv[4], tol))) {
        fprintf(stderr, "usage: %s %s N_STEPS H [NEWTON_TOL [state]] (%s, N_STEPS whole "
                        "numbers >= 1; H, NEWTON_TOL > 0)\n", argv[0], what, what);
        return 2;
    }
    return 0;
}

#endif
