/* SUNDIALS IDA driven from C, with the residual and iteration matrix compiled in.
 *
 * integrators/sundials.py generates `res` and `jac` from the system's JAX functions
 * (linalg/codegen.py) and prepends them to this file; the steps then run without Python
 * between IDA and the callbacks. The settings are those scikit-sundae applies for
 * `integrators.ida.IDA` (same calls, same order).
 * The declarations below are SUNDIALS 7's (sunrealtype double, sunindextype int), the
 * build that scikit-sundae's wheel ships and this file is linked against.
 */
#include <stdio.h>
#include <stdlib.h>

typedef double sunrealtype;
typedef int sunindextype;
typedef int SUNComm;
typedef void *N_Vector, *SUNMatrix, *SUNLinearSolver, *SUNContext;
typedef int (*IDAResFn)(sunrealtype, N_Vector, N_Vector, N_Vector, void *);
typedef int (*IDALsJacFn)(sunrealtype, sunrealtype, N_Vector, N_Vector, N_Vector, SUNMatrix,
                          void *, N_Vector, N_Vector, N_Vector);

int SUNContext_Create(SUNComm comm, SUNContext *ctx);
int SUNContext_Free(SUNContext *ctx);
int SUNContext_ClearErrHandlers(SUNContext ctx);
typedef void (*SUNErrHandlerFn)(int, const char *, const char *, const char *, int, void *,
                                SUNContext);
int SUNContext_PushErrHandler(SUNContext ctx, SUNErrHandlerFn fn, void *data);
N_Vector N_VNew_Serial(sunindextype n, SUNContext ctx);
sunrealtype *N_VGetArrayPointer(N_Vector v);
void N_VDestroy(N_Vector v);
SUNMatrix SUNDenseMatrix(sunindextype m, sunindextype n, SUNContext ctx);
sunrealtype *SUNDenseMatrix_Data(SUNMatrix a);
void SUNMatDestroy(SUNMatrix a);
SUNLinearSolver SUNLinSol_Dense(N_Vector y, SUNMatrix a, SUNContext ctx);
int SUNLinSolFree(SUNLinearSolver s);
void *IDACreate(SUNContext ctx);
int IDAInit(void *mem, IDAResFn res, sunrealtype t0, N_Vector y0, N_Vector yp0);
int IDASetUserData(void *mem, void *data);
int IDASVtolerances(void *mem, sunrealtype rtol, N_Vector atol);
int IDASetLinearSolver(void *mem, SUNLinearSolver s, SUNMatrix a);
int IDASetJacFn(void *mem, IDALsJacFn jac);
int IDASetMaxNonlinIters(void *mem, int n);
int IDASetMaxConvFails(void *mem, int n);
int IDASetId(void *mem, N_Vector id);
int IDASetInitStep(void *mem, sunrealtype h);
int IDASetMinStep(void *mem, sunrealtype h);
int IDASetMaxStep(void *mem, sunrealtype h);
int IDASetMaxOrd(void *mem, int order);
int IDASetMaxNumSteps(void *mem, long int n);
int IDASetStopTime(void *mem, sunrealtype t);
int IDASolve(void *mem, sunrealtype tout, sunrealtype *tret, N_Vector y, N_Vector yp, int task);
int IDAGetNumResEvals(void *mem, long int *n);
int IDAGetNumJacEvals(void *mem, long int *n);
void IDAFree(void **mem);

#define IDA_ONE_STEP 2

typedef struct {
    int neq;
    long calls, trials;
    double t_trial;
    void *mem;
    SUNContext ctx;
    N_Vector y, yp, atol, id;
    SUNMatrix a;
    SUNLinearSolver ls;
    char message[512]; /* SUNDIALS' text for the last error */
} Solver;

static void error_handler(int line, const char *function, const char *file, const char *msg,
                          int code, void *data, SUNContext ctx)
{
    Solver *s = data;
    snprintf(s->message, sizeof s->message, "[%s, Error: %d] %s", function, code, msg);
}

static int residual_callback(sunrealtype t, N_Vector y, N_Vector yp, N_Vector r, void *data)
{
    Solver *s = data;
    s->calls++;
    /* A step attempt is a residual at a new time (integrators.ida.Callbacks: the same count
     * as the Python driver's). */
    if (s->trials == 0 || t != s->t_trial) {
        s->trials++;
        s->t_trial = t;
    }
    res(t, N_VGetArrayPointer(y), N_VGetArrayPointer(yp), N_VGetArrayPointer(r));
    return 0;
}

static int jacobian_callback(sunrealtype t, sunrealtype cj, N_Vector y, N_Vector yp,
                             N_Vector r, SUNMatrix a, void *data, N_Vector t1, N_Vector t2,
                             N_Vector t3)
{
    jac(t, N_VGetArrayPointer(y), N_VGetArrayPointer(yp), cj, SUNDenseMatrix_Data(a));
    return 0;
}

static void copy(N_Vector v, const double *x, int n)
{
    double *d = N_VGetArrayPointer(v);
    for (int i = 0; i < n; i++) d[i] = x[i];
}

void solver_free(Solver *s)
{
    if (!s) return;
    if (s->mem) IDAFree(&s->mem);
    if (s->ls) SUNLinSolFree(s->ls);
    if (s->a) SUNMatDestroy(s->a);
    N_Vector *vs[] = {&s->y, &s->yp, &s->atol, &s->id};
    for (int i = 0; i < 4; i++)
        if (*vs[i]) N_VDestroy(*vs[i]);
    if (s->ctx) SUNContext_Free(&s->ctx);
    free(s);
}

/* A solver at (t0, y0, yp0), or NULL with *flag the first failing call's flag. `id` marks
 * differential (1) and algebraic (0) components, as IDASetId takes it. */
Solver *solver_new(int neq, double t0, const double *y0, const double *yp0, double rtol,
                   const double *atol, const double *id, int use_jacobian, int max_order,
                   long max_steps, int max_nonlin_iters, int max_conv_fails,
                   double first_step, double min_step, double max_step, double tstop,
                   int *flag)
{
    Solver *s = calloc(1, sizeof(Solver));
    *flag = -1;
    if (!s) return NULL;
    s->neq = neq;
    if ((*flag = SUNContext_Create(0, &s->ctx)) < 0) goto fail;
    *flag = -1;
    s->y = N_VNew_Serial(neq, s->ctx);
    s->yp = N_VNew_Serial(neq, s->ctx);
    s->atol = N_VNew_Serial(neq, s->ctx);
    s->id = N_VNew_Serial(neq, s->ctx);
    if (!s->y || !s->yp || !s->atol || !s->id) goto fail;
    copy(s->y, y0, neq);
    copy(s->yp, yp0, neq);
    copy(s->atol, atol, neq);
    copy(s->id, id, neq);
    s->a = SUNDenseMatrix(neq, neq, s->ctx);
    s->ls = SUNLinSol_Dense(s->y, s->a, s->ctx);
    s->mem = IDACreate(s->ctx);
    *flag = -1;
    if (!s->mem || !s->a || !s->ls) goto fail;
    /* SUNDIALS' errors come back as flags; its text is kept for the run's message. */
    SUNContext_ClearErrHandlers(s->ctx);
    SUNContext_PushErrHandler(s->ctx, error_handler, s);
    if ((*flag = IDASetUserData(s->mem, s)) < 0) goto fail;
    if ((*flag = IDAInit(s->mem, residual_callback, t0, s->y, s->yp)) < 0) goto fail;
    if ((*flag = IDASVtolerances(s->mem, rtol, s->atol)) < 0) goto fail;
    if ((*flag = IDASetLinearSolver(s->mem, s->ls, s->a)) < 0) goto fail;
    if (use_jacobian && (*flag = IDASetJacFn(s->mem, jacobian_callback)) < 0) goto fail;
    if ((*flag = IDASetMaxNonlinIters(s->mem, max_nonlin_iters)) < 0) goto fail;
    if ((*flag = IDASetMaxConvFails(s->mem, max_conv_fails)) < 0) goto fail;
    if ((*flag = IDASetId(s->mem, s->id)) < 0) goto fail;
    if ((*flag = IDASetInitStep(s->mem, first_step)) < 0) goto fail;
    if ((*flag = IDASetMinStep(s->mem, min_step)) < 0) goto fail;
    if ((*flag = IDASetMaxStep(s->mem, max_step)) < 0) goto fail;
    if ((*flag = IDASetMaxOrd(s->mem, max_order)) < 0) goto fail;
    if ((*flag = IDASetMaxNumSteps(s->mem, max_steps)) < 0) goto fail;
    if ((*flag = IDASetStopTime(s->mem, tstop)) < 0) goto fail;
    return s;
fail:
    solver_free(s);
    return NULL;
}

/* Internal steps towards tstop, each written to (t_out, y_out), until tstop, `room` steps
 * or a failure. Returns the number written; *flag is IDASolve's last flag and *t the time
 * it returned (on a failure, where IDA stopped). */
int solver_steps(Solver *s, double tstop, int room, double *t_out, double *y_out, int *flag,
                 double *t)
{
    int k = 0;
    *flag = 0;
    while (k < room) {
        *flag = IDASolve(s->mem, tstop, t, s->y, s->yp, IDA_ONE_STEP);
        if (*flag < 0) break;
        const double *y = N_VGetArrayPointer(s->y);
        t_out[k] = *t;
        for (int i = 0; i < s->neq; i++) y_out[(long)k * s->neq + i] = y[i];
        k++;
        if (*t >= tstop) break;
    }
    return k;
}

/* The current state, after a failure (IDA leaves y at the last successful step). */
void solver_state(Solver *s, double *y)
{
    const double *d = N_VGetArrayPointer(s->y);
    for (int i = 0; i < s->neq; i++) y[i] = d[i];
}

/* Work counts: residual calls, step attempts, IDA's residual evaluations and
 * iteration-matrix evaluations. */
void solver_counts(Solver *s, long *out)
{
    out[0] = s->calls;
    out[1] = s->trials;
    IDAGetNumResEvals(s->mem, out + 2);
    IDAGetNumJacEvals(s->mem, out + 3);
}

const char *solver_message(Solver *s)
{
    return s->message;
}
