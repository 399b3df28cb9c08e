
/* ---- The deployed controller: one call per sample period ------------------------------------------------
 * Scenario '@SCENARIO@', @N@ joints, @RESN@ reservoir units, rate @RATE@ Hz (period 1/@RATE@ s); torque
 * @TAUMAX@.
 *
 *   @P@state s;                      fixed size, no pointers: copy it, store it, put it in static memory
 *   @P@init(&s);                     once: the scenario's initial x_esn and w_hat
 *   rc = @P@step(&s, t, q, dq, tau); every period: tau from the measurements, then s advances one period
 *
 * Arguments of @P@step:
 *   s    @P@state*            controller state, advanced by one period on success (unchanged on error)
 *   t    double               time since the start of the reference [s]
 *   q    const double[@N@]      joint positions [rad; m for a prismatic joint]
 *   dq   const double[@N@]      joint velocities [rad/s; m/s]
 *   tau  double[@N@]            out: joint torques to apply until the next call [N m; N]
 * Returns 0 inside both funnels, 1 outside a funnel (tau is then the design's torque at the state projected
 * onto @CLIP@ of the funnel: finite), -1 for a null pointer, -2 for a non-finite t, q or dq, -3 when the
 * result is not finite (s unchanged).
 * Update: x_esn and w_hat by the exponential Euler method (the linear decay -leak/time_constant x and
 * -Gamma sigma W exact over the period, the rest held): stable at every period; see docs/derivation.md.
 * No global state: each controller instance (or thread) needs only its own @P@state.
 */
#define @UP@N_JOINTS @N@
#define @UP@N_ESN @NESN@
#define @UP@N_REGRESSOR @NREG@
/* entries of x_esn and rows of w_hat in a recorded trajectory row (0: the design has none; the state then
   keeps a one-entry placeholder that stays 0) */
#define @UP@ROW_ESN @RESN@
#define @UP@ROW_REGRESSOR @RREG@
#define @UP@RATE_HZ @RATE@

typedef struct {
  double x_esn[@NESN@];     /* reservoir state [-] */
  double w_hat[@NW@];     /* ESN output weights, (@NREG@ x @N@) column-major */
  double margin[2 * @N@];   /* last 1 - |e|/F per joint: e1 then e2 (< 0: outside that funnel) */
  double qd[@N@];           /* last reference position [rad; m] */
  double t;               /* time of the last step [s] */
  long steps;             /* successful steps since @P@init */
} @P@state;

/* sizeof(@P@state) in bytes. */
int @P@state_size(void);
/* Set s to the scenario's initial state; 0 on success, -1 for a null pointer. */
int @P@init(@P@state *s);
/* One sample period (see above). */
int @P@step(@P@state *s, double t, const double *q, const double *dq, double *tau);
