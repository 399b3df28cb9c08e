/* The sampled-data loop of symfunnel.deployed.engine in C, with MuJoCo as the plant: measurements (noise,
 * quantisation), the generated step, zero-order hold with optional one-sample delay, the dead zone on the held
 * torque, and between samples `substeps` calls of MuJoCo's mj_step. The plant's friction and disturbance, which
 * MuJoCo does not model, enter as a passive force evaluated at every step or RK4 stage (mjcb_passive), so the
 * engine integrates the same ODE as symfunnel's plant. With slopes on (implicitfast), the callback also puts the
 * force's slope in dq into the joint's damping, which MuJoCo's implicit step then treats implicitly (the damper's
 * force from it is cancelled: only the derivative is used), a linearly implicit Euler step for the stiff friction.
 * MuJoCo's functions and callback slots are passed in as pointers (no link against libmujoco); only the struct
 * layouts come from its headers (version @MJVERSION@). */
#include <math.h>
#include <string.h>
#include <mujoco/mujoco.h>

#define SFS_MAX_N 64

typedef int (*sfs_step_fn)(void *state, double t, const double *q, const double *dq, double *tau);
typedef int (*sfs_casadi_fn)(const double **arg, double **res, int *iw, double *w, int mem);
typedef void (*sfs_mj_step_fn)(const mjModel *m, mjData *d);
typedef void (*sfs_warning_fn)(const char *msg);

/* A compiled CasADi function with its argument buffers (inputs are written through arg[i]). */
typedef struct {
  sfs_casadi_fn f;
  const double **arg;
  double **res;
  int *iw;
  double *w;
} sfs_fun;

/* mjcb_passive has no user pointer: the callback's context is this file's (one loop at a time per process; the
 * caller holds a lock). force: arg[0] = t, arg[1] = q (n), arg[2] = dq (n), arg[3] = plant parameters;
 * res[0] = generalized force (n) added to qfrc_passive, res[1] = its slopes in dq (n, >= 0; used with slopes on). */
static const sfs_fun *g_force = 0;
static const int *g_qadr = 0, *g_dadr = 0;
static int g_n = 0, g_force_failed = 0, g_slopes = 0;
static double g_base_damping[SFS_MAX_N];
static char g_warning[512];
static int g_warnings = 0;

int sfs_mj_header_version(void) { return mjVERSION_HEADER; }

/* Slopes on or off for the next loop; base: the engine's own damping per joint (restored when the loop ends). */
void sfs_mj_set_slopes(int on, const double *base, int n) {
  int i;
  g_slopes = on;
  for (i = 0; i < n && i < SFS_MAX_N; ++i) g_base_damping[i] = base[i];
}

const char *sfs_mj_last_warning(void) { return g_warning; }

int sfs_mj_warning_count(void) { return g_warnings; }

/* MuJoCo's default warning handler appends to MUJOCO_LOG.TXT in the working directory: keep the text instead. */
static void sfs_warning(const char *msg) {
  strncpy(g_warning, msg, sizeof g_warning - 1);
  g_warning[sizeof g_warning - 1] = 0;
  ++g_warnings;
}

static void sfs_passive(const mjModel *m, mjData *d) {
  double *t = (double *) g_force->arg[0], *q = (double *) g_force->arg[1], *dq = (double *) g_force->arg[2];
  const double *f = g_force->res[0];
  int i;
  (void) m;
  *t = d->time;
  for (i = 0; i < g_n; ++i) {
    q[i] = d->qpos[g_qadr[i]];
    dq[i] = d->qvel[g_dadr[i]];
  }
  if (g_force->f(g_force->arg, g_force->res, g_force->iw, g_force->w, 0)) {
    g_force_failed = 1;
    return;
  }
  if (!g_slopes) {
    for (i = 0; i < g_n; ++i) d->qfrc_passive[g_dadr[i]] += f[i];
    return;
  }
  for (i = 0; i < g_n; ++i) {
    double *damping = &((mjModel *) m)->dof_damping[g_dadr[i]];
    /* mj_passive's damper already applied -(damping) dq with the slope of the last call: take that part out */
    d->qfrc_passive[g_dadr[i]] += f[i] + (*damping - g_base_damping[i]) * dq[i];
    *damping = g_base_damping[i] + g_force->res[1][i];
  }
}

/* Returns 0 at the end, 1 when stopped after leaving a funnel, the step's code (< 0) on its error, -100 when a
 * plant function failed, -101 for too many joints, -102 when the engine's state is not finite.
 * applied (may be NULL: no dead zone): arg[0] = tau (n), arg[1] = plant parameters; res[0] = applied torque (n).
 * force (may be NULL: no friction or disturbance): see sfs_passive. cb_slot / warn_slot: the addresses of
 * MuJoCo's mjcb_passive and mju_user_warning, restored before returning.
 * X: (K+1) x 2n states, row 0 set by the caller and equal to the engine's state; TAU: K x n applied torques
 * (before the dead zone, as symfunnel's loop records them). */
int sfs_mj_loop(sfs_step_fn step, void *state, sfs_mj_step_fn mj_step_, mjfGeneric *cb_slot,
                sfs_warning_fn *warn_slot, const mjModel *m, mjData *d, int substeps, const int *qadr,
                const int *dadr, int n, const sfs_fun *applied, const sfs_fun *force, long K, double h,
                const double *nq, const double *ndq, double resolution, int delay, int stop_on_breach, double *X,
                double *TAU, long *k_end, long *outside) {
  double qm[SFS_MAX_N], dqm[SFS_MAX_N], tau[SFS_MAX_N], pending[SFS_MAX_N], u[SFS_MAX_N];
  mjfGeneric saved_cb = *cb_slot;
  sfs_warning_fn saved_warn = *warn_slot;
  long k;
  int i, s, rc = 0;
  *outside = -1;
  *k_end = 0;
  if (n > SFS_MAX_N) return -101;
  g_force = force;
  g_qadr = qadr;
  g_dadr = dadr;
  g_n = n;
  g_force_failed = 0;
  g_warnings = 0;
  g_warning[0] = 0;
  *cb_slot = force ? sfs_passive : 0;
  *warn_slot = sfs_warning;
  for (i = 0; i < n; ++i) pending[i] = 0.0;
  for (i = 0; i < m->nv; ++i) d->qfrc_applied[i] = 0.0;
  for (k = 0; k < K; ++k) {
    const double *x = X + k * 2 * n;
    double *xn = X + (k + 1) * 2 * n;
    double t = (double) k * h;
    for (i = 0; i < n; ++i) {
      qm[i] = x[i] + (nq ? nq[k * n + i] : 0.0);
      if (resolution > 0.0) qm[i] = resolution * round(qm[i] / resolution);
      dqm[i] = x[n + i] + (ndq ? ndq[k * n + i] : 0.0);
    }
    rc = step(state, t, qm, dqm, tau);
    if (rc < 0) {
      *k_end = k;
      break;
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
    if (applied) {
      memcpy((double *) applied->arg[0], u, n * sizeof(double));
      if (applied->f(applied->arg, applied->res, applied->iw, applied->w, 0)) {
        *k_end = k;
        rc = -100;
        break;
      }
      for (i = 0; i < n; ++i) d->qfrc_applied[dadr[i]] = applied->res[0][i];
    } else {
      for (i = 0; i < n; ++i) d->qfrc_applied[dadr[i]] = u[i];
    }
    d->time = t;                               /* each period starts at its exact sample time */
    for (s = 0; s < substeps; ++s) mj_step_(m, d);
    if (g_force_failed) {
      *k_end = k;
      rc = -100;
      break;
    }
    for (i = 0; i < n; ++i) {
      xn[i] = d->qpos[qadr[i]];
      xn[n + i] = d->qvel[dadr[i]];
    }
    for (i = 0; i < 2 * n; ++i) {
      if (!isfinite(xn[i])) break;
    }
    if (i < 2 * n) {
      *k_end = k + 1;
      rc = -102;
      break;
    }
    if (stop_on_breach && *outside >= 0 && k - *outside >= 1) {
      *k_end = k + 1;
      rc = 1;
      break;
    }
  }
  if (k == K) {
    *k_end = K;
    rc = 0;
  }
  if (g_slopes)
    for (i = 0; i < n; ++i) ((mjModel *) m)->dof_damping[dadr[i]] = g_base_damping[i];
  g_slopes = 0;
  *cb_slot = saved_cb;
  *warn_slot = saved_warn;
  return rc;
}
