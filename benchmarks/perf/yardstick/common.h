/* What the C yardsticks share: the max-norm, a clock in seconds, and the parsing of their
 * numeric arguments (one clear refusal instead of a silent zero). */
#ifndef YARDSTICK_COMMON_H
#define YARDSTICK_COMMON_H

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

/* max_i |x_i| over n entries. */
static inline double norm_of(const double *x, int n) {
    double m = 0.0;
    for (int i = 0; i < n; i++) {
        const double a = fabs(x[i]);
        m = a > m ? a : m;
    }
    return m;
}

/* The time of `clock` (CLOCK_MONOTONIC, CLOCK_PROCESS_CPUTIME_ID) in seconds. */
static inline double seconds_of(clockid_t clock) {
    struct timespec t;
    clock_gettime(clock, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}

/* A finite number, the whole of `s`. */
static inline int parse_double(const char *s, double *out) {
    char *end;
    *out = strtod(s, &end);
    return *s != '\0' && *end == '\0' && isfinite(*out);
}

/* A positive integer, the whole of `s`. */
static inline int parse_long(const char *s, long *out) {
    char *end;
    *out = strtol(s, &end, 10);
    return *s != '\0' && *end == '\0' && *out >= 1;
}

/* argv[1..n] as numbers into out; 0, or 2 (the usage error's status) after naming on
 * stderr the first argument that is not one. */
static inline int parse_numbers(char **argv, int n, double *out) {
    for (int i = 0; i < n; i++) {
        char *end;
        out[i] = strtod(argv[1 + i], &end);
        if (*argv[1 + i] == '\0' || *end != '\0') {
            fprintf(stderr, "%s: argument %d (%s) is not a number\n", argv[0], 1 + i,
                    argv[1 + i]);
            return 2;
        }
    }
    return 0;
}

#endif
