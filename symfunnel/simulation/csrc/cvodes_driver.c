/* symfunnel's CVODES driver: the closed loop integrated by CVODES (the SUNDIALS build inside CasADi's wheel) called
 * from C, with the Newton iteration's linear algebra on the Jacobian's fixed sparsity pattern.
 *
 * Why: through casadi.integrator every right-hand side and Jacobian is a CasADi function call (two process-clock
 * reads each, and an MX wrapper on CasADi's virtual machine around the generated code), and every Newton
 * refactorisation redoes CSparse's symbolic analysis (cs_lu's depth-first searches) and its allocations. Here the
 * generated functions are called directly, and I - gamma J is factorised by a left-looking LU whose fill pattern is
 * computed once, in the state order the closed loop already chose so that the LU fills in little (controller
 * states first, joints last), with the diagonal as pivots.
 *
 * The algorithm is CasADi's (simulation/runner.py's casadi.integrator with linear_solver "csparse"): the same
 * CVODES calls and options (BDF, Newton, scalar tolerances, max_num_steps, max_step_size, CV_NORMAL output at
 * every grid point with the stop time at the last one, CVodeReInit per call), and the same linear solver contract
 * (each setup evaluates J at the predicted state; a solve uses the last factorisation, without a gamma
 * correction). Without pivoting, the LU is backward stable as long as the entries do not grow in the elimination;
 * a zero or non-finite pivot, or a growth factor above SF_GROWTH_MAX (backward error ~ n eps growth: at most
 * ~1e-6 relative, which the Newton iteration absorbs) makes the setup fail recoverably: CVODES then retries with a
 * smaller step, where I - gamma J is closer to I. (The pivots themselves may be tiny against their column: the
 * joint columns of the funnel loop have pivot 1 beside entries of 1e9 at t = 0, and the elimination is exact
 * block elimination there, without growth.)
 *
 * sf_run_hist / sf_sample: the same integration in CV_ONE_STEP mode, every step's Nordsieck array kept, so that
 * the samples between output points are interpolated (CVodeGetDky, as CV_NORMAL does at an output point) once the
 * chunk's step count has said how dense they must be, instead of integrating the chunk again.
 */
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include "cvodes_mem.h"
#include "sf_lu.h"
#include "sf_nvec.h"

static int sf_wide_vectors = 1;  /* sf_set_wide_vectors */
static int sf_fused_dky = 1;     /* sf_set_fused_dky */

typedef long long int casadi_int;     /* the closed loop's generated code uses CasADi's default casadi_int */
typedef int (*sf_fun)(const double **arg, double **res, casadi_int *iw, double *w, int mem);

/* The CVODES API symfunnel uses (cvodes.h, nvector_serial.h of SUNDIALS 2.6.1) */
void *CVodeCreate(int lmm, int iter);
int CVodeInit(void *mem, CVRhsFn f, realtype t0, N_Vector y0);
int CVodeReInit(void *mem, realtype t0, N_Vector y0);
int CVodeSStolerances(void *mem, realtype reltol, realtype abstol);
int CVodeSetErrHandlerFn(void *mem, CVErrHandlerFn ehfun, void *eh_data);
int CVodeSetUserData(void *mem, void *user_data);
int CVodeSetMaxNumSteps(void *mem, long int mxsteps);
int CVodeSetMaxStep(void *mem, realtype hmax);
int CVodeSetMaxOrd(void *mem, int maxord);
int CVodeSetStopTime(void *mem, realtype tstop);
int CVode(void *mem, realtype tout, N_Vector yout, realtype *tret, int itask);
int CVodeGetIntegratorStats(void *mem, long int *nsteps, long int *nfevals, long int *nlinsetups,
                            long int *netfails, int *qlast, int *qcur, realtype *hinused, realtype *hlast,
                            realtype *hcur, realtype *tcur);
int CVodeGetNonlinSolvStats(void *mem, long int *nniters, long int *nncfails);
char *CVodeGetReturnFlagName(long int flag);
int CVodeGetDky(void *mem, realtype t, int k, N_Vector dky);
void N_VSetArrayPointer(realtype *v_data, N_Vector v);
void N_VScale(realtype c, N_Vector x, N_Vector z);
void CVodeFree(void **mem);
N_Vector N_VMake_Serial(long int length, realtype *data);
void N_VDestroy_Serial(N_Vector v);
realtype *N_VGetArrayPointer(N_Vector v);
void N_VLinearSum(realtype a, N_Vector x, realtype b, N_Vector y, N_Vector z);
void N_VAbs(N_Vector x, N_Vector z);
void N_VInv(N_Vector x, N_Vector z);
void N_VAddConst(N_Vector x, realtype b, N_Vector z);
realtype N_VMin(N_Vector x);

#define SF_BDF 2
#define SF_NEWTON 2
#define SF_NORMAL 1
#define SF_ONE_STEP 2

/* ---- the solver object --------------------------------------------------------------------------------- */

typedef struct {
  int nx, np, jac_n_in, jac_n_out, jac_out, nnzJ;
  sf_fun ode, jac;
  const double **arg;
  double **res;
  casadi_int *iw;
  double *w, *p, *Jx;
  sf_lu lu;
  void *mem;
  N_Vector y;
  long njac, npivfail;
  int wide;                      /* 1: its vectors run sf_nvec.h's operations */
  char msg[400];
  /* the last sf_run_hist's steps: each one's tn, h, hu, q and Nordsieck array zn[0..q] (hist_z from hist_off) */
  double *hist_t, *hist_h, *hist_hu, *hist_z;
  int *hist_q;
  size_t *hist_off, hist_n, hist_cap, hist_zlen, hist_zcap;
  int hist_ok;
  N_Vector hist_v[L_MAX];
  /* the order the states are written out in (out[j] = y[order[j]]: the caller's public order, so that no copy
   * of every output array is permuted afterwards), or NULL for CVODES' own; scratch: one state for it */
  int *order;
  double *scratch;
  N_Vector scratch_v;
} sf_solver;

/* One state y (CVODES' order) into out, in the output order. */
static void sf_put(const sf_solver *s, const double *y, double *out) {
  int j;
  if (!s->order) { memcpy(out, y, (size_t) s->nx * sizeof(double)); return; }
  for (j = 0; j < s->nx; ++j) out[j] = y[s->order[j]];
}

static void sf_ehfun(int error_code, const char *module, const char *function, char *msg, void *data) {
  sf_solver *s = (sf_solver *) data;
  (void) error_code; (void) module; (void) function;
  strncpy(s->msg, msg ? msg : "", sizeof s->msg - 1);
  s->msg[sizeof s->msg - 1] = '\0';
}

static int sf_rhs(realtype t, N_Vector y, N_Vector ydot, void *data) {
  sf_solver *s = (sf_solver *) data;
  s->arg[0] = &t;
  s->arg[1] = N_VGetArrayPointer(y);
  s->arg[2] = 0;
  s->arg[3] = s->p;
  s->arg[4] = 0;
  s->res[0] = N_VGetArrayPointer(ydot);
  s->res[1] = s->res[2] = s->res[3] = 0;
  return s->ode(s->arg, s->res, s->iw, s->w, 0) ? 1 : 0;
}

static int sf_lsetup(struct CVodeMemRec *cv_mem, int convfail, N_Vector ypred, N_Vector fpred,
                     booleantype *jcurPtr, N_Vector t1, N_Vector t2, N_Vector t3) {
  sf_solver *s = (sf_solver *) cv_mem->cv_lmem;
  double t = cv_mem->cv_tn;
  int i;
  (void) convfail; (void) fpred; (void) t1; (void) t2; (void) t3;
  for (i = 0; i < s->jac_n_in; ++i) s->arg[i] = 0;
  for (i = 0; i < s->jac_n_out; ++i) s->res[i] = 0;
  s->arg[0] = &t;
  s->arg[1] = N_VGetArrayPointer(ypred);
  s->arg[3] = s->p;
  s->res[s->jac_out] = s->Jx;
  s->njac++;
  if (s->jac(s->arg, s->res, s->iw, s->w, 0)) return 1;
  *jcurPtr = TRUE;
  if (sf_lu_factor(&s->lu, s->Jx, s->nnzJ, cv_mem->cv_gamma)) {
    s->npivfail++;
    return 1;
  }
  return 0;
}

static int sf_lsolve(struct CVodeMemRec *cv_mem, N_Vector b, N_Vector weight, N_Vector ycur, N_Vector fcur) {
  sf_solver *s = (sf_solver *) cv_mem->cv_lmem;
  (void) weight; (void) ycur; (void) fcur;
  sf_lu_solve(&s->lu, N_VGetArrayPointer(b));
  return 0;
}

void sf_free(void *handle) {
  sf_solver *s = (sf_solver *) handle;
  if (!s) return;
  if (s->mem) CVodeFree(&s->mem);
  if (s->y) N_VDestroy_Serial(s->y);
  sf_lu_free(&s->lu);
  free(s->arg); free(s->res); free(s->iw); free(s->w); free(s->p); free(s->Jx);
  free(s->order); free(s->scratch);
  if (s->scratch_v) N_VDestroy_Serial(s->scratch_v);
  free(s->hist_t); free(s->hist_h); free(s->hist_hu); free(s->hist_z); free(s->hist_q); free(s->hist_off);
  {
    int j;
    for (j = 0; j < L_MAX; ++j) if (s->hist_v[j]) N_VDestroy_Serial(s->hist_v[j]);
  }
  free(s);
}

/* The memory block read through the vendored layout must show what the public setters just wrote, at fields
 * spread over the whole block (before, in and after the linear-solver section). */
static int sf_check_layout(const sf_solver *s, double rtol, double atol, long max_steps, double max_step,
                           int max_order) {
  const struct CVodeMemRec *m = (const struct CVodeMemRec *) s->mem;
  return m->cv_uround == DBL_EPSILON && m->cv_f == sf_rhs && m->cv_user_data == s && m->cv_lmm == SF_BDF
      && m->cv_iter == SF_NEWTON && m->cv_reltol == rtol && m->cv_Sabstol == atol && m->cv_quadr == FALSE
      && m->cv_sensi == FALSE && m->cv_tstopset == TRUE && m->cv_tstop == 0.5 && m->cv_qmax == max_order
      && m->cv_mxstep == max_steps && m->cv_maxcor == 3 && m->cv_maxnef == 7 && m->cv_maxncf == 10
      && m->cv_mxhnil == 10 && m->cv_hmin == 0.0 && m->cv_hmax_inv == (max_step > 0 ? 1.0 / max_step : 0.0)
      && m->cv_nlscoef == 0.1 && m->cv_linit == 0 && m->cv_lsetup == 0 && m->cv_lsolve == 0 && m->cv_lfree == 0
      && m->cv_lmem == 0 && m->cv_setupNonNull == FALSE && m->cv_MallocDone == TRUE && m->cv_QuadMallocDone == FALSE
      && m->cv_ehfun == sf_ehfun && m->cv_eh_data == (const void *) s && m->cv_sldeton == FALSE
      && m->cv_nrtfn == 0 && m->cv_gfun == 0 && m->cv_mxgnull == 1 && m->cv_adj == FALSE && m->cv_adj_mem == 0
      && m->cv_adjMallocDone == FALSE;
}

/* sizes: ode (sz_arg, sz_res, sz_iw, sz_w), jac (the same), then jac's n_in, n_out and the index of jac_ode_x.
 * Jp, Ji: jac_ode_x's pattern (CSC, nx + 1 and Jp[nx] entries). Returns the solver, or NULL with err set. */
void *sf_create(int nx, int np, void *ode, void *jac, const long long *sizes, const int *Jp, const int *Ji,
                double rtol, double atol, long max_steps, double max_step, int max_order, char *err, int errlen) {
  sf_solver *s = calloc(1, sizeof *s);
  long long sz_arg, sz_res, sz_iw, sz_w;
  int i;
#define SF_FAIL(text) do { strncpy(err, text, (size_t) errlen - 1); err[errlen - 1] = '\0'; sf_free(s); return 0; } while (0)
  if (!s) SF_FAIL("out of memory");
  s->nx = nx;
  s->np = np;
  memcpy(&s->ode, &ode, sizeof s->ode);      /* object to function pointer, without ISO C's cast warning */
  memcpy(&s->jac, &jac, sizeof s->jac);
  sz_arg = sizes[0] > sizes[4] ? sizes[0] : sizes[4];
  sz_res = sizes[1] > sizes[5] ? sizes[1] : sizes[5];
  sz_iw = sizes[2] > sizes[6] ? sizes[2] : sizes[6];
  sz_w = sizes[3] > sizes[7] ? sizes[3] : sizes[7];
  s->jac_n_in = (int) sizes[8];
  s->jac_n_out = (int) sizes[9];
  s->jac_out = (int) sizes[10];
  if (sz_arg < 5 || sz_res < 4 || s->jac_n_in > sz_arg || s->jac_n_out > sz_res || s->jac_out >= s->jac_n_out)
    SF_FAIL("unexpected function signature");
  s->nnzJ = Jp[nx];
  s->arg = calloc((size_t) sz_arg, sizeof(double *));
  s->res = calloc((size_t) sz_res, sizeof(double *));
  s->iw = calloc((size_t) (sz_iw > 0 ? sz_iw : 1), sizeof(casadi_int));
  s->w = calloc((size_t) (sz_w > 0 ? sz_w : 1), sizeof(double));
  s->p = calloc((size_t) (np > 0 ? np : 1), sizeof(double));
  s->Jx = calloc((size_t) (s->nnzJ > 0 ? s->nnzJ : 1), sizeof(double));
  if (!s->arg || !s->res || !s->iw || !s->w || !s->p || !s->Jx) SF_FAIL("out of memory");
  if (sf_lu_analyse(&s->lu, nx, Jp, Ji)) SF_FAIL("the Jacobian's pattern cannot be factorised in place");
  s->y = N_VMake_Serial(nx, calloc((size_t) nx, sizeof(double)));
  if (s->y && sf_wide_vectors) s->wide = sf_nv_install(s->y);    /* before CVodeInit: its clones copy the table */
  s->scratch = calloc((size_t) nx, sizeof(double));
  if (!s->y || !s->scratch) SF_FAIL("out of memory");
  s->scratch_v = N_VMake_Serial(nx, s->scratch);
  if (!s->scratch_v) SF_FAIL("out of memory");
  if (s->wide) sf_nv_install(s->scratch_v);
  s->mem = CVodeCreate(SF_BDF, SF_NEWTON);
  if (!s->mem) SF_FAIL("CVodeCreate failed");
  if (CVodeSetErrHandlerFn(s->mem, sf_ehfun, s) || CVodeSetUserData(s->mem, s)
      || CVodeInit(s->mem, sf_rhs, 0.0, s->y) || CVodeSStolerances(s->mem, rtol, atol)
      || CVodeSetMaxNumSteps(s->mem, max_steps) || (max_step > 0 && CVodeSetMaxStep(s->mem, max_step))
      || (max_order > 0 && CVodeSetMaxOrd(s->mem, max_order)) || CVodeSetStopTime(s->mem, 0.5))
    SF_FAIL(s->msg[0] ? s->msg : "setting up CVODES failed");
  if (!sf_check_layout(s, rtol, atol, max_steps, max_step, max_order > 0 ? max_order : 5))
    SF_FAIL("CVODES' memory layout is not the one this driver was written for");
  {
    struct CVodeMemRec *m = (struct CVodeMemRec *) s->mem;
    m->cv_lmem = s;
    m->cv_lsetup = sf_lsetup;
    m->cv_lsolve = sf_lsolve;
    m->cv_setupNonNull = TRUE;
  }
  for (i = 0; i < nx; ++i) N_VGetArrayPointer(s->y)[i] = 0.0;
  return s;
#undef SF_FAIL
}

/* The chunk's statistics (steps, rhs evaluations, linear setups, error-test failures, Newton iterations, Newton
 * convergence failures, Jacobian evaluations, pivot failures) into stats; returns 0, or CVODES' flag (< 0) with
 * msg = 'CVode returned "NAME"'. */
static int sf_finish(sf_solver *s, int flag, long *stats, char *msg, int msglen) {
  double hinused, hlast, hcur, tcur;
  long nsteps = 0, nfevals = 0, nlinsetups = 0, netfails = 0, nniters = 0, nncfails = 0;
  int qlast, qcur;
  CVodeGetIntegratorStats(s->mem, &nsteps, &nfevals, &nlinsetups, &netfails, &qlast, &qcur, &hinused, &hlast,
                          &hcur, &tcur);
  CVodeGetNonlinSolvStats(s->mem, &nniters, &nncfails);
  stats[0] = nsteps; stats[1] = nfevals; stats[2] = nlinsetups; stats[3] = netfails;
  stats[4] = nniters; stats[5] = nncfails; stats[6] = s->njac; stats[7] = s->npivfail;
  if (flag < 0) {
    char *name = CVodeGetReturnFlagName(flag);
    int len = 0;
    strncpy(msg, "CVode returned \"", (size_t) msglen - 1);
    msg[msglen - 1] = '\0';
    len = (int) strlen(msg);
    strncpy(msg + len, name ? name : "?", (size_t) (msglen - len - 1));
    msg[msglen - 1] = '\0';
    len = (int) strlen(msg);
    if (len < msglen - 1) { msg[len] = '"'; msg[len + 1] = '\0'; }
    free(name);
    return flag;
  }
  return 0;
}

/* Integrate from x0 at relative time 0 over grid[0..K-1] (relative times, ascending) with parameters p (np values:
 * the chunk's start time, then the plant's); X (K x nx, row k = the state at grid[k]). stats: steps, rhs
 * evaluations, linear setups, error-test failures, Newton iterations, Newton convergence failures, Jacobian
 * evaluations, pivot failures. Returns 0, or CVODES' flag (< 0) with msg = 'CVode returned "NAME"'. */
int sf_run(void *handle, const double *p, const double *x0, int K, const double *grid, double *X, long *stats,
           char *msg, int msglen) {
  sf_solver *s = (sf_solver *) handle;
  double *y = N_VGetArrayPointer(s->y), t = 0.0, tret = 0.0;
  int k, flag = 0;
  memcpy(s->p, p, (size_t) s->np * sizeof(double));
  memcpy(y, x0, (size_t) s->nx * sizeof(double));
  s->njac = s->npivfail = 0;
  s->msg[0] = '\0';
  msg[0] = '\0';
  flag = CVodeReInit(s->mem, 0.0, s->y);
  for (k = 0; flag >= 0 && k < K; ++k) {
    flag = CVodeSetStopTime(s->mem, grid[K - 1]);
    if (flag >= 0 && fabs(t - grid[k]) >= 1e-9) flag = CVode(s->mem, grid[k], s->y, &tret, SF_NORMAL);
    if (flag < 0) break;
    t = grid[k];
    sf_put(s, y, X + (size_t) k * (size_t) s->nx);
  }
  return sf_finish(s, flag, stats, msg, msglen);
}

/* The order states are written out in from now on: out[j] = y[order[j]] (a permutation of 0..nx-1), or CVODES'
 * own with order NULL. 0, or 1 when order is not a permutation. */
int sf_set_order(void *handle, const int *order) {
  sf_solver *s = (sf_solver *) handle;
  int j, *o = 0;
  char *seen;
  if (order) {
    o = malloc((size_t) s->nx * sizeof(int));
    seen = calloc((size_t) s->nx, 1);
    if (!o || !seen) { free(o); free(seen); return 1; }
    for (j = 0; j < s->nx; ++j) {
      if (order[j] < 0 || order[j] >= s->nx || seen[order[j]]) { free(o); free(seen); return 1; }
      seen[order[j]] = 1;
      o[j] = order[j];
    }
    free(seen);
  }
  free(s->order);
  s->order = o;
  return 0;
}

/* Which factorisation setups use from now on: 1, sf_lu_factor_columns (the previous one, kept as the reference);
 * 0, sf_lu_factor (the same factors, faster). */
void sf_set_lu_columns(void *handle, int columns) {
  ((sf_solver *) handle)->lu.columns = columns;
}

/* Whether solvers created from now on install sf_nvec.h's vector operations (1, where they apply) or keep
 * SUNDIALS' (0, the previous path); and whether a solver has them. */
void sf_set_wide_vectors(int wide) {
  sf_wide_vectors = wide;
}
int sf_has_wide_vectors(void *handle) {
  return ((sf_solver *) handle)->wide;
}

/* One vector operation on serial vectors over x, y, z (length n), through CVODES' dispatch, with sf_nvec.h's
 * operations installed (wide 1) or SUNDIALS' own (0): op 0 N_VLinearSum(a, x, b, y, z), 1 N_VScale(a, x, z), 2
 * N_VAbs, 3 N_VInv, 4 N_VAddConst(x, a, z), 5 N_VMin(x) into *r; alias 1: z is x, 2: z is y. For tests. Returns
 * whether the wide operations were installed, or -1. */
int sf_nv_apply(int op, double a, double b, long n, double *x, double *y, double *z, int alias, int wide, double *r) {
  N_Vector X = N_VMake_Serial(n, x), Y = N_VMake_Serial(n, y), Z = N_VMake_Serial(n, z), W;
  int on = 0;
  if (!X || !Y || !Z) { if (X) N_VDestroy_Serial(X); if (Y) N_VDestroy_Serial(Y); if (Z) N_VDestroy_Serial(Z); return -1; }
  W = alias == 1 ? X : alias == 2 ? Y : Z;
  if (wide) on = sf_nv_install(X) & sf_nv_install(Y) & sf_nv_install(Z);
  if (op == 0) N_VLinearSum(a, X, b, Y, W);
  else if (op == 1) N_VScale(a, X, W);
  else if (op == 2) N_VAbs(X, W);
  else if (op == 3) N_VInv(X, W);
  else if (op == 4) N_VAddConst(X, a, W);
  else *r = N_VMin(X);
  N_VDestroy_Serial(X); N_VDestroy_Serial(Y); N_VDestroy_Serial(Z);
  return on;
}

/* The largest growth factor of the factorisations so far (0 before the first), for the tests. */
double sf_max_growth(void *handle) {
  return ((sf_solver *) handle)->lu.max_growth;
}

/* Factorise I - gamma J for given J values and solve for b in place (0, or 1 on a pivot failure): for tests. */
int sf_factor_solve(void *handle, const double *Jx, double gamma, double *b) {
  sf_solver *s = (sf_solver *) handle;
  if (sf_lu_factor(&s->lu, Jx, s->nnzJ, gamma)) return 1;
  sf_lu_solve(&s->lu, b);
  return 0;
}

/* ---- one chunk, its samples chosen after it: the history of its steps ----------------------------------- */

/* dst[0..n-1] = src[0..n-1], written past the caches where the processor can (SSE2's non-temporal stores, 16-byte
 * aligned): a chunk's history (MBs, read once after the chunk by sf_sample) then does not evict CVODES' own
 * vectors and LU from the caches at every step. */
static void sf_copy_stream(double *dst, const double *src, size_t n) {
#if defined(__GNUC__) && defined(__x86_64__)
  size_t i = 0;
  if (((size_t) dst & 15) != 0) { dst[0] = src[0]; i = 1; }
  for (; i + 2 <= n; i += 2) _mm_stream_pd(dst + i, _mm_loadu_pd(src + i));
  for (; i < n; ++i) dst[i] = src[i];
#else
  memcpy(dst, src, n * sizeof(double));
#endif
}

/* Keep the step CVODES has just taken (tn, h, hu, q, zn[0..q]); 0 when the history would pass max_bytes or memory
 * runs out (the history is then incomplete and sf_sample refuses). */
static int sf_hist_push(sf_solver *s, double max_bytes) {
  struct CVodeMemRec *m = (struct CVodeMemRec *) s->mem;
  size_t nx = (size_t) s->nx, need = (size_t) (m->cv_q + 1) * nx, j;
  if ((double) (s->hist_zlen + need) * sizeof(double) > max_bytes) return 0;
  if (s->hist_n == s->hist_cap) {
    size_t cap = s->hist_cap ? 2 * s->hist_cap : 256;
    double *t = realloc(s->hist_t, cap * sizeof *t);
    if (t) s->hist_t = t;
    double *h = realloc(s->hist_h, cap * sizeof *h);
    if (h) s->hist_h = h;
    double *hu = realloc(s->hist_hu, cap * sizeof *hu);
    if (hu) s->hist_hu = hu;
    int *q = realloc(s->hist_q, cap * sizeof *q);
    if (q) s->hist_q = q;
    size_t *off = realloc(s->hist_off, cap * sizeof *off);
    if (off) s->hist_off = off;
    if (!t || !h || !hu || !q || !off) return 0;
    s->hist_cap = cap;
  }
  if (s->hist_zlen + need > s->hist_zcap) {
    size_t cap = s->hist_zcap ? 2 * s->hist_zcap : 64 * need;
    double *z;
    while (cap < s->hist_zlen + need) cap *= 2;
    z = realloc(s->hist_z, cap * sizeof *z);
    if (!z) return 0;
    s->hist_z = z;
    s->hist_zcap = cap;
  }
  s->hist_t[s->hist_n] = m->cv_tn;
  s->hist_h[s->hist_n] = m->cv_h;
  s->hist_hu[s->hist_n] = m->cv_hu;
  s->hist_q[s->hist_n] = m->cv_q;
  s->hist_off[s->hist_n] = s->hist_zlen;
  for (j = 0; j <= (size_t) m->cv_q; ++j)
    sf_copy_stream(s->hist_z + s->hist_zlen + j * nx, N_VGetArrayPointer(m->cv_zn[j]), nx);
  s->hist_zlen += need;
  s->hist_n++;
  return 1;
}

/* sf_run's integration (the same CVODES calls: the steps, the output points and the statistics are sf_run's, bit
 * for bit), stepping in CV_ONE_STEP mode so that every step is kept (at most max_bytes of Nordsieck arrays): the
 * samples between the output points can then be chosen after the chunk, from its step count, and taken by
 * sf_sample exactly as CVode would have interpolated them -- instead of integrating the chunk again on a denser
 * grid. CV_NORMAL returns at the first step reaching each output point and interpolates there (CVodeGetDky);
 * here the same step is followed by the same CVodeGetDky. Returns 0; CVODES' flag (< 0); or 1 where this driver
 * does not reproduce CV_NORMAL (an output point within 1e-9 of the one before, or the step limit per output point
 * reached: CVODES' own message comes from sf_run) -- the caller then uses sf_run. */
int sf_run_hist(void *handle, const double *p, const double *x0, int K, const double *grid, double *X, long *stats,
                char *msg, int msglen, double max_bytes) {
  sf_solver *s = (sf_solver *) handle;
  struct CVodeMemRec *m = (struct CVodeMemRec *) s->mem;
  double *y = N_VGetArrayPointer(s->y), tret = 0.0, prev = 0.0;
  long nstloc = 0;
  int k = 0, flag = 0, j;
  if (!s->hist_v[0]) {
    for (j = 0; j < L_MAX; ++j) {
      s->hist_v[j] = N_VMake_Serial(s->nx, y);
      if (!s->hist_v[j]) return 1;
      if (s->wide) sf_nv_install(s->hist_v[j]);
    }
  }
  for (k = 0; k < K; ++k) {
    if (fabs(grid[k] - prev) < 1e-9) return 1;
    prev = grid[k];
  }
  memcpy(s->p, p, (size_t) s->np * sizeof(double));
  memcpy(y, x0, (size_t) s->nx * sizeof(double));
  s->njac = s->npivfail = 0;
  s->msg[0] = '\0';
  msg[0] = '\0';
  s->hist_n = s->hist_zlen = 0;
  s->hist_ok = 1;
  flag = CVodeReInit(s->mem, 0.0, s->y);
  if (flag >= 0) flag = CVodeSetStopTime(s->mem, grid[K - 1]);
  k = 0;
  while (flag >= 0 && k < K) {
    if (m->cv_mxstep > 0 && nstloc >= m->cv_mxstep) return 1;
    flag = CVode(s->mem, grid[k], s->y, &tret, SF_ONE_STEP);    /* tout: the first call's initial step, as sf_run's */
    if (flag < 0) break;
    nstloc++;
    if (s->hist_ok) s->hist_ok = sf_hist_push(s, max_bytes);
    while (k < K && (m->cv_tn - grid[k]) * m->cv_h >= 0.0) {
      if (CVodeGetDky(s->mem, grid[k], 0, s->scratch_v) != 0) return 1;
      sf_put(s, s->scratch, X + (size_t) k * (size_t) s->nx);
      ++k;
      nstloc = 0;
    }
  }
#if defined(__GNUC__) && defined(__x86_64__)
  _mm_sfence();                     /* the history's streamed stores ordered before whoever samples it next */
#endif
  return sf_finish(s, flag, stats, msg, msglen);
}

/* The states at the relative times t[0..M-1] (ascending, inside the last sf_run_hist's chunk) into Y (M x nx):
 * each from the first kept step reaching it, by CVodeGetDky on that step's tn, h, hu, q and Nordsieck array --
 * the value CVode in CV_NORMAL mode returns for that time as an output point. 0, or 1 (history incomplete, or a
 * time outside the chunk). CVODES' memory is as before afterwards. */
int sf_sample_rows(void *handle, int M, const double *t, double *Y, const long *rows);

int sf_sample(void *handle, int M, const double *t, double *Y) {
  return sf_sample_rows(handle, M, t, Y, 0);
}

/* CVodeGetDky(t, k = 0) of SUNDIALS 2.6.1 on one kept step (tn, h, hu, q, its Nordsieck columns zn[0..q]), then
 * sf_put into out: the same test of t against the step, the same s = (t - tn)/h, and per element the same
 * operations in the same order -- N_VScale(1, zn[q]) a copy, then for j = q-1..0 N_VLinearSum(1, zn[j], s, dky,
 * dky), whose cases (axpy for s = 1, a difference for s = -1, else s dky + zn[j]) each give the double
 * s v + zn[j][i] (no fused multiply-add: -std=c99 keeps contraction off) -- so the same doubles, in one pass
 * (sf_horner) instead of a copy and q passes through CVODES' vector operations. 0, or 1 where CVodeGetDky returns
 * CV_BAD_T. */
static int sf_dky_put(sf_solver *s, double tn, double h, double hu, int q, const double *const *zn, double t,
                      double *out) {
  double tfuzz = 100.0 * ((struct CVodeMemRec *) s->mem)->cv_uround * (fabs(tn) + fabs(hu)), tp, tn1, sc;
  if (hu < 0.0) tfuzz = -tfuzz;
  tp = tn - hu - tfuzz;
  tn1 = tn + tfuzz;
  if ((t - tp) * (t - tn1) > 0.0) return 1;
  sc = (t - tn) / h;
#if SF_NV_SIMD
  if (s->wide) sf_horner(sc, zn, q, s->scratch, s->nx);
  else
#endif
    sf_horner_scalar(sc, zn, q, s->scratch, s->nx);
  sf_put(s, s->scratch, out);
  return 0;
}

void sf_set_fused_dky(int fused) {
  sf_fused_dky = fused;
}

/* sf_sample writing sample i into row rows[i] of Y (rows NULL: row i): the samples straight into their places in
 * time order among the output points, without a second copy. */
int sf_sample_rows(void *handle, int M, const double *t, double *Y, const long *rows) {
  sf_solver *s = (sf_solver *) handle;
  struct CVodeMemRec *m = (struct CVodeMemRec *) s->mem;
  N_Vector zn[L_MAX];
  double tn = m->cv_tn, h = m->cv_h, hu = m->cv_hu;
  int q = m->cv_q, i, j, rc = 0;
  size_t step = 0, nx = (size_t) s->nx;
  if (!s->hist_ok || !s->hist_v[0]) return 1;
  memcpy(zn, m->cv_zn, sizeof zn);
  for (i = 0; i < M && rc == 0; ++i) {
    while (step < s->hist_n && (s->hist_t[step] - t[i]) * s->hist_h[step] < 0.0) ++step;
    if (step == s->hist_n || (i > 0 && t[i] < t[i - 1])) { rc = 1; break; }
    if (sf_fused_dky) {
      const double *z[L_MAX];
      for (j = 0; j <= s->hist_q[step]; ++j) z[j] = s->hist_z + s->hist_off[step] + (size_t) j * nx;
      rc = sf_dky_put(s, s->hist_t[step], s->hist_h[step], s->hist_hu[step], s->hist_q[step], z, t[i],
                      Y + (size_t) (rows ? rows[i] : i) * nx);
      continue;
    }
    m->cv_tn = s->hist_t[step];
    m->cv_h = s->hist_h[step];
    m->cv_hu = s->hist_hu[step];
    m->cv_q = s->hist_q[step];
    for (j = 0; j <= m->cv_q; ++j) {
      N_VSetArrayPointer(s->hist_z + s->hist_off[step] + (size_t) j * nx, s->hist_v[j]);
      m->cv_zn[j] = s->hist_v[j];
    }
    if (CVodeGetDky(s->mem, t[i], 0, s->scratch_v) != 0) rc = 1;
    else sf_put(s, s->scratch, Y + (size_t) (rows ? rows[i] : i) * nx);
  }
  memcpy(m->cv_zn, zn, sizeof zn);
  m->cv_tn = tn; m->cv_h = h; m->cv_hu = hu; m->cv_q = q;
  return rc;
}
