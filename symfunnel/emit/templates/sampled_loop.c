/* The sampled-data loop of symfunnel.deployed.loop in C: measurements (noise, quantisation), the generated step,
 * zero-order hold with optional one-sample delay, and the compiled plant step between samples.
 * The step and the plant are passed in as function pointers (the compiled generated step API and CasADi's C API
 * of the plant function), so this file knows neither. */
#include <math.h>
#include <string.h>

#define SFS_MAX_N 64

typedef int (*sfs_step_fn)(void *state, double t, const double *q, const double *dq, double *tau);
typedef int (*sfs_casadi_fn)(const double **arg, double **res, int *iw, double *w, int mem);

/* Returns 0 at the end, 1 when stopped after leaving a funnel, the step's code (< 0) on its error, -100 when the
 * plant function failed, -101 for too many joints. k_end: samples done; outside: first sample outside (or -1).
 * Plant arguments: arg[0] = t0 (1), arg[1] = x (2n), arg[2] = tau (n); res[0] = x at t0 + h (2n), res[1] (when MB
 * is not NULL) = the smallest true margins over the plant's steps within the period (2n).
 * X: (K+1) x 2n states, row 0 set by the caller; TAU: K x n applied torques; MB: K x 2n or NULL. */
int sfs_loop(sfs_step_fn step, void *state, sfs_casadi_fn plant, const double **arg, double **res, int *iw,
             double *w, int n, long K, double h, const double *nq, const double *ndq, double resolution,
             int delay, int stop_on_breach, double *X, double *TAU, double *MB, long *k_end, long *outside) {
  double qm[SFS_MAX_N], dqm[SFS_MAX_N], tau[SFS_MAX_N], pending[SFS_MAX_N];
  double *t0 = (double *) arg[0], *xin = (double *) arg[1], *u = (double *) arg[2];
  const double *xf = res[0];
  long k;
  int i, rc;
  *outside = -1;
  *k_end = 0;
  if (n > SFS_MAX_N) return -101;
  for (i = 0; i < n; ++i) pending[i] = 0.0;
  for (k = 0; k < K; ++k) {
    const double *x = X + k * 2 * n;
    double t = (double) k * h;
    for (i = 0; i < n; ++i) {
      qm[i] = x[i] + (nq ? nq[k * n + i] : 0.0);
      if (resolution > 0.0) qm[i] = resolution * round(qm[i] / resolution);
      dqm[i] = x[n + i] + (ndq ? ndq[k * n + i] : 0.0);
    }
    rc = step(state, t, qm, dqm, tau);
    if (rc < 0) {
      *k_end = k;
      return rc;
    }
    if (rc == 1 && *outside < 0) *outside = k;
    for (i = 0; i < n; ++i) {
      if (delay) {
        u[i] = pending[i];
        pending[i] = tau[i];
      } else {
        u[i] = tau[i];
      }
      TAU[k * n + i] = u[i];
    }
    *t0 = t;
    memcpy(xin, x, 2 * n * sizeof(double));
    if (plant(arg, res, iw, w, 0)) {
      *k_end = k;
      return -100;
    }
    memcpy(X + (k + 1) * 2 * n, xf, 2 * n * sizeof(double));
    if (MB) memcpy(MB + k * 2 * n, res[1], 2 * n * sizeof(double));
    if (stop_on_breach && *outside >= 0 && k - *outside >= 1) {
      *k_end = k + 1;
      return 1;
    }
  }
  *k_end = K;
  return 0;
}
