
/* ---- The deployed controller (see @BASENAME@.h): state, initial state and one period ------------------- */
#include <math.h>
#include <stdint.h>
#include <string.h>
#include "@BASENAME@.h"

#define @UP@SZ_(n) ((n) > 0 ? (n) : 1)

static const double @P@x_esn0_[@NESN@] = {@X0@};
static const double @P@w_hat0_[@NW@] = {@W0@};
/* exponential-Euler weights (1 - exp(-l h)) / l of x_esn_dot and w_hat_dot at h = 1/@RATE@ s */
static const double @P@etd_[2] = {@ETD@};

/* 1 when every v[i] is finite: the exponent field is all ones exactly for inf and NaN; integer and, add, or
 * over the bit patterns (no branch per value), which the compiler vectorises. */
static int @P@all_finite_(const double *v, int n) {
  uint64_t acc = 0, b;
  int i;
  for (i = 0; i < n; ++i) {
    memcpy(&b, v + i, sizeof b);
    acc |= (b & UINT64_C(0x7FF0000000000000)) + UINT64_C(0x0010000000000000);   /* bit 63 set iff the exponent is all ones */
  }
  return !(acc >> 63);
}

int @P@state_size(void) {
  return (int) sizeof(@P@state);
}

int @P@init(@P@state *s) {
  int i;
  if (!s) return -1;
  memcpy(s->x_esn, @P@x_esn0_, sizeof s->x_esn);
  memcpy(s->w_hat, @P@w_hat0_, sizeof s->w_hat);
  for (i = 0; i < 2 * @N@; ++i) s->margin[i] = 1.0;
  for (i = 0; i < @N@; ++i) s->qd[i] = 0.0;
  s->t = 0.0;
  s->steps = 0;
  return 0;
}

int @P@step(@P@state *s, double t, const double *q, const double *dq, double *tau) {
  const casadi_real *arg[@UP@SZ_(@F@step_core_SZ_ARG)];
  casadi_real *res[@UP@SZ_(@F@step_core_SZ_RES)];
  casadi_int iw[@UP@SZ_(@F@step_core_SZ_IW)];
  casadi_real w[@UP@SZ_(@F@step_core_SZ_W)];
  double x_next[@NESN@], w_next[@NW@], margin[2 * @N@], qd[@N@], tau_out[@N@];
  int i, rc = 0;
  if (!s || !q || !dq || !tau) return -1;
  if (!isfinite(t)) return -2;
  for (i = 0; i < @N@; ++i)
    if (!isfinite(q[i]) || !isfinite(dq[i])) return -2;
  arg[0] = &t;
  arg[1] = q;
  arg[2] = dq;
  arg[3] = s->x_esn;
  arg[4] = s->w_hat;
  arg[5] = @P@etd_;
  res[0] = tau_out;
  res[1] = x_next;
  res[2] = w_next;
  res[3] = margin;
  res[4] = qd;
  if (@F@step_core(arg, res, iw, w, 0)) return -3;
  if (!@P@all_finite_(tau_out, @N@) || !@P@all_finite_(x_next, @NESN@) || !@P@all_finite_(w_next, @NW@)) return -3;
  for (i = 0; i < 2 * @N@; ++i)
    if (!(margin[i] > 0.0)) rc = 1;
  memcpy(tau, tau_out, sizeof tau_out);
  memcpy(s->x_esn, x_next, sizeof x_next);
  memcpy(s->w_hat, w_next, sizeof w_next);
  memcpy(s->margin, margin, sizeof margin);
  memcpy(s->qd, qd, sizeof qd);
  s->t = t;
  s->steps += 1;
  return rc;
}
