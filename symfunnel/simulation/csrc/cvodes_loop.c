/* symfunnel's run loop in C: the chunks of `simulation.run.simulate` that end without a stop -- CVODES on the
 * chunk's output grid keeping its steps, the samples between output points at the chunk's own density, the logged
 * signals at every sample (the closed loop's `<name>_many`), the first-bad-sample test, the margin scan between
 * samples with its dips, the refined output steps, and the extremes between output points -- in one call, so that
 * no Python runs between chunks.
 *
 * It is a transcription of run.py's chunk (`_refine_chunk`, `Between.update`, `bad_index`, `scan_dips`,
 * runner.py's `_dense_from_steps` / `_with_first_step`), operation for operation in the same order, so that its
 * results are those of the Python loop bit for bit. Where that loop would stop or take another path -- a sample
 * with a margin <= 0 or a non-finite value, a refined step that leaves a funnel, a CVODES failure, a chunk the kept
 * steps do not reproduce -- nothing of the chunk is kept and the call returns SF_LOOP_HANDOVER: the caller runs
 * that chunk with the Python loop (which locates the breach or failure), then calls again.
 */
#define _POSIX_C_SOURCE 199309L      /* clock_gettime */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef long long int sf_cint;
typedef int (*sf_many)(sf_cint T, const double **in, double **out);

int sf_run(void *handle, const double *p, const double *x0, int K, const double *grid, double *X, long *stats,
           char *msg, int msglen);
int sf_run_hist(void *handle, const double *p, const double *x0, int K, const double *grid, double *X, long *stats,
                char *msg, int msglen, double max_bytes);
int sf_sample(void *handle, int M, const double *t, double *Y);
int sf_sample_rows(void *handle, int M, const double *t, double *Y, const long *rows);

#define SF_LOOP_DONE 0
#define SF_LOOP_HANDOVER 1
#define SF_LOOP_SLICE 2
#define SF_LOOP_TIMEOUT 3
#define SF_LOOP_NOMEM (-1)

/* Integer settings (ints[]), by index */
enum { I_M, I_NX, I_N, I_NP, I_NOUT, I_IM1, I_IM2, I_ITAU, I_ITAUA, I_Q0, I_DQ0, I_BETWEEN_MAX, I_SCAN_POINTS,
       I_MAX_REFINED, I_REFINE_POINTS, I_FIXED, I_NCHUNK, I_IN_PLACE, I_NINTS };
/* Real settings (reals[]), by index */
enum { R_H, R_TF, R_LIMIT, R_ELAPSED0, R_SLICE, R_SCAN_DIP, R_HISTORY_BYTES, R_NREALS };
/* State (in and out): ints k, K, sub, points, density, refined, unchecked; reals lowest, integrate time */
enum { S_K, S_KC, S_SUB, S_POINTS, S_DENSITY, S_REFINED, S_UNCHECKED, S_DONE, S_NSTATE };

typedef struct { double *m1, *m2, *t_m1, *t_m2, *tau, *t_tau, *tau_applied; long points, density, refined; } sf_between;

typedef struct {
  void *cv;
  sf_many outputs, margins;
  const int *ints, *perm, *nnz_out, *chunks;
  const double *reals, *pvals;
  int nx, n, np, nout, nnz_all;
  double *p;                         /* [chunk start; pvals] */
  long stats[8], chunk[8];          /* the last integration's statistics; the chunk's own */
  char msg[200];
  double integ;                      /* seconds inside CVODES */
} sf_loop;

static double sf_now(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double) ts.tv_sec + 1e-9 * (double) ts.tv_nsec;
}

typedef char sf_long_fits_a_double[sizeof(long) <= sizeof(double) ? 1 : -1];  /* index arrays in sf_buf */

/* A growable scratch array; growing it drops its contents (no caller keeps them across a larger request, and
 * realloc's copy of the old contents was 1.6 % of the paper run) */
typedef struct { double *v; size_t cap; } sf_buf;
static double *sf_need(sf_buf *b, size_t n) {
  if (n > b->cap) {
    free(b->v);
    b->cap = 0;
    b->v = malloc((n > 0 ? n : 1) * sizeof(double));
    if (!b->v) return 0;
    b->cap = n;
  }
  return b->v;
}

/* between.density: a power of two at or above steps / points, 1..max */
static int sf_density(long steps, int points, int max) {
  double ratio = (double) steps / (double) (points > 1 ? points : 1);
  int s = 1;
  if (!(ratio > 1)) return 1;
  s = (int) ceil(log2(ratio) - 1e-12);
  if (s < 0) s = 0;
  if (s > 30) return max;
  s = 1 << s;
  return s < max ? s : max;
}

/* the logged signals at T points (t, X row-major public order) into O (nout blocks, each T x nnz column-major) */
static int sf_outputs(sf_loop *L, sf_cint T, const double *t, const double *X, double *O) {
  const double *in[3];
  double *out[64];
  int i;
  size_t off = 0;
  if (L->nout > 64) return 1;
  in[0] = t; in[1] = X; in[2] = L->pvals;
  for (i = 0; i < L->nout; ++i) { out[i] = O + off; off += (size_t) T * (size_t) L->nnz_out[i]; }
  if (T == 0) return 0;
  return L->outputs(T, in, out);
}

static const double *sf_out(const sf_loop *L, const double *O, sf_cint T, int which) {
  size_t off = 0;
  int i;
  for (i = 0; i < which; ++i) off += (size_t) T * (size_t) L->nnz_out[i];
  return O + off;
}

/* breach.bad_index: the first sample with a non-finite state, m1, m2 or tau, or a margin <= 0; -1 when none */
static long sf_bad_index(const sf_loop *L, const double *O, sf_cint T, const double *X) {
  const double *m1 = sf_out(L, O, T, L->ints[I_IM1]), *m2 = sf_out(L, O, T, L->ints[I_IM2]);
  const double *tau = sf_out(L, O, T, L->ints[I_ITAU]);
  int n = L->n, j;
  sf_cint i;
  for (i = 0; i < T; ++i) {
    for (j = 0; j < L->nx; ++j) if (!isfinite(X[(size_t) i * L->nx + j])) return (long) i;
    for (j = 0; j < n; ++j) {
      double a = m1[(size_t) j * T + i], b = m2[(size_t) j * T + i], c = tau[(size_t) j * T + i];
      if (!isfinite(a) || !isfinite(b) || !isfinite(c) || !(a > 0) || !(b > 0)) return (long) i;
    }
  }
  return -1;
}

/* Between.update on samples [a, b) of the T in O (times t) */
static void sf_between_update(const sf_loop *L, sf_between *B, const double *t, const double *O, sf_cint T,
                              const long *order, long Kc, int sub) {
  int n = L->n, j, which;
  sf_cint i, a = 0, b = T, cnt = 0;
  for (i = 0; i < T; ++i) if (!order || order[i] >= Kc) ++cnt;
  if (cnt == 0) return;
  B->points += (long) cnt;
  if (sub) { if (sub > B->density) B->density = sub; }
  else B->refined++;
  for (which = 0; which < 2; ++which) {
    const double *m = sf_out(L, O, T, L->ints[which ? I_IM2 : I_IM1]);
    double *best = which ? B->m2 : B->m1, *when = which ? B->t_m2 : B->t_m1;
    for (j = 0; j < n; ++j) {
      double v = INFINITY;
      sf_cint iv = a;
      for (i = a; i < b; ++i) {
        double x = m[(size_t) j * T + i];
        if (order && order[i] < Kc) continue;
        if (!isfinite(x)) x = INFINITY;
        if (x < v) { v = x; iv = i; }
      }
      if (v < best[j]) { best[j] = v; when[j] = t[iv]; }
    }
  }
  for (which = 0; which < 2; ++which) {
    const double *m = sf_out(L, O, T, L->ints[which ? I_ITAUA : I_ITAU]);
    double *best = which ? B->tau_applied : B->tau, *when = which ? 0 : B->t_tau;
    for (j = 0; j < n; ++j) {
      double v = -INFINITY;
      sf_cint iv = a;
      for (i = a; i < b; ++i) {
        double x = fabs(m[(size_t) j * T + i]);
        if (order && order[i] < Kc) continue;
        if (!isfinite(x)) x = -INFINITY;
        if (x > v) { v = x; iv = i; }
      }
      if (v > best[j]) { best[j] = v; if (when) when[j] = t[iv]; }
    }
  }
}

/* MarginScan.__call__: the margins at SCAN_POINTS - 1 points of each gap between consecutive samples (t, X: T),
 * the joint state linearly interpolated: times into ts ((T-1)(S-1)), margins into Mg ((T-1)(S-1) x width, column-
 * major, as `_many` writes them) */
static int sf_scan(sf_loop *L, sf_cint T, const double *t, const double *X, sf_buf *bts, sf_buf *bq, sf_buf *bdq,
                   sf_buf *bm) {
  int S = L->ints[I_SCAN_POINTS], n = L->n, q0 = L->ints[I_Q0], dq0 = L->ints[I_DQ0], j, c;
  sf_cint G = T > 0 ? (T - 1) * (S - 1) : 0, g, r;
  double *ts = sf_need(bts, (size_t) G), *Q = sf_need(bq, (size_t) G * n), *DQ = sf_need(bdq, (size_t) G * n);
  double *Mg = sf_need(bm, (size_t) G * 2 * n);
  const double *in[4];
  double *out[1];
  if (!ts || !Q || !DQ || !Mg) return -1;
  if (G == 0) return 0;
  for (g = 0; g + 1 < T; ++g) {
    const double *xa = X + (size_t) g * L->nx, *xb = xa + L->nx;
    for (j = 1; j < S; ++j) {
      double w = (double) j / (double) S;
      r = g * (S - 1) + (j - 1);
      ts[r] = t[g] + (t[g + 1] - t[g]) * w;
      for (c = 0; c < n; ++c) {
        Q[(size_t) r * n + c] = xa[q0 + c] + (xb[q0 + c] - xa[q0 + c]) * w;
        DQ[(size_t) r * n + c] = xa[dq0 + c] + (xb[dq0 + c] - xa[dq0 + c]) * w;
      }
    }
  }
  in[0] = ts; in[1] = Q; in[2] = DQ; in[3] = L->pvals;
  out[0] = Mg;
  return L->margins(G, in, out) ? 1 : 0;
}

/* numpy's min of values (NaN if any is NaN) */
static double sf_npmin(double a, double b) {
  if (isnan(a) || isnan(b)) return NAN;
  return b < a ? b : a;
}

/* numpy's fmin (NaN only when both are) */
static double sf_fmin(double a, double b) {
  if (isnan(a)) return b;
  if (isnan(b)) return a;
  return b < a ? b : a;
}

/* order[0..n-1] sorted by key[order[i]], equal keys in their given order (numpy's stable argsort): a bottom-up
 * merge sort, tmp n entries of scratch */
static void sf_stable_sort(const double *key, long *order, long *tmp, long n) {
  long width, i, *src = order, *dst = tmp, *t;
  for (width = 1; width < n; width *= 2) {
    for (i = 0; i < n; i += 2 * width) {
      long a = i, mid = i + width < n ? i + width : n, end = i + 2 * width < n ? i + 2 * width : n, b = mid, o = i;
      while (a < mid && b < end) dst[o++] = key[src[b]] < key[src[a]] ? src[b++] : src[a++];
      while (a < mid) dst[o++] = src[a++];
      while (b < end) dst[o++] = src[b++];
    }
    t = src; src = dst; dst = t;
  }
  if (src != order) memcpy(order, src, (size_t) n * sizeof(long));
}

/* searchsorted(tc, v, "left"): the number of tc below v */
static long sf_left(const double *tc, int K, double v) {
  long lo = 0, hi = K;
  while (lo < hi) { long mid = (lo + hi) / 2; if (tc[mid] < v) lo = mid + 1; else hi = mid; }
  return lo;
}

/* CVODES from (t0, x public order) over relative grid[0..K-1], the states into X (public order); 0 or failure */
static int sf_integrate(sf_loop *L, double t0, const double *x, int K, const double *grid, double *X, double *xp,
                        int hist, int *nsteps) {
  int i, rc;
  double c0 = sf_now();
  L->p[0] = t0;
  memcpy(L->p + 1, L->pvals, (size_t) (L->np - 1) * sizeof(double));
  for (i = 0; i < L->nx; ++i) xp[i] = x[L->perm[i]];
  if (hist)
    rc = sf_run_hist(L->cv, L->p, xp, K, grid, X, L->stats, L->msg, (int) sizeof L->msg, L->reals[R_HISTORY_BYTES]);
  else
    rc = sf_run(L->cv, L->p, xp, K, grid, X, L->stats, L->msg, (int) sizeof L->msg);
  L->integ += sf_now() - c0;
  if (nsteps) *nsteps = (int) L->stats[0];
  return rc;
}

typedef struct {
  sf_buf grid, X, tb, Xb, X1, ta, Xa, order, O, tsc, Qsc, DQsc, Msc, tr, Xr, Or, tg, Xg, xp, samp, rel, g1, rows;
} sf_work;

static void sf_work_free(sf_work *w) {
  sf_buf *b = (sf_buf *) w;
  size_t i;
  for (i = 0; i < sizeof *w / sizeof(sf_buf); ++i) free(b[i].v);
}

/* One refined output step (run.py's `refine` and the scan inside it): from (t_a, x_a) over hq on REFINE_POINTS
 * points; 0 when its samples were taken (or its integration failed: skipped), 1 when the run stops in it (the
 * caller hands the chunk over), -1 out of memory. */
static int sf_refine(sf_loop *L, sf_work *w, sf_between *B, double t_a, const double *x_a, double hq) {
  int R = L->ints[I_REFINE_POINTS], nx = L->nx, i;
  double step = hq / (double) R;
  double *grid = sf_need(&w->grid, (size_t) R), *X = sf_need(&w->Xr, (size_t) R * nx), *t = sf_need(&w->tr, R);
  double *O = sf_need(&w->Or, (size_t) R * L->nnz_all), *xp = sf_need(&w->xp, nx);
  double *tg = sf_need(&w->tg, (size_t) R + 1), *Xg = sf_need(&w->Xg, (size_t) (R + 1) * nx);
  if (!grid || !X || !t || !O || !xp || !tg || !Xg) return -1;
  for (i = 0; i < R; ++i) grid[i] = step * (double) (i + 1);
  if (sf_integrate(L, t_a, x_a, R, grid, X, xp, 0, 0)) return 0;
  for (i = 0; i < R; ++i) t[i] = t_a + step * (double) (i + 1);
  if (sf_outputs(L, R, t, X, O)) return 1;
  if (sf_bad_index(L, O, R, X) >= 0) return 1;
  tg[0] = t_a;
  memcpy(tg + 1, t, (size_t) R * sizeof(double));
  memcpy(Xg, x_a, (size_t) nx * sizeof(double));
  memcpy(Xg + nx, X, (size_t) R * nx * sizeof(double));
  {
    int rc = sf_scan(L, R + 1, tg, Xg, &w->tsc, &w->Qsc, &w->DQsc, &w->Msc), width = 2 * L->n;
    int S = L->ints[I_SCAN_POINTS];
    sf_cint G = (sf_cint) R * (S - 1), r;
    double lo = NAN;
    if (rc) return rc < 0 ? -1 : 1;
    for (r = 0; r < G; ++r) {            /* flat = sm.min(axis=2); nanmin(flat) <= 0 stops */
      double v = w->Msc.v[r];
      int c;
      for (c = 1; c < width; ++c) v = sf_npmin(v, w->Msc.v[(size_t) c * G + r]);
      if (!isnan(v) && (isnan(lo) || v < lo)) lo = v;
    }
    if (!isnan(lo) && lo <= 0) return 1;
  }
  sf_between_update(L, B, t, O, R, 0, 0, 0);
  return 0;
}

/* One chunk from (k, x) of Kc output points: 0 kept (its outputs written at row `row` of the run's arrays), 1 handed
 * over, -1 out of memory. */
static int sf_chunk(sf_loop *L, sf_work *w, long k, int Kc, const double *x, sf_between *B, double *lowest,
                    int *sub, long *unchecked, double *t_out, double *X_out, double *O_out,
                    sf_cint rows, sf_cint row) {
  int nx = L->nx, n = L->n, i, j, c, s, nsteps = 0, BM = L->ints[I_BETWEEN_MAX], Kn, used;
  double h = L->reals[R_H], t0 = (double) k * h, hs;
  double *grid = sf_need(&w->grid, (size_t) Kc), *X = sf_need(&w->X, (size_t) Kc * nx), *xp = sf_need(&w->xp, nx);
  double *tb, *Xb, *ta, *Xa, *O, *samp;
  double *tc;
  long nb = 0, Ta, *order, bi;
  if (!grid || !X || !xp) return -1;
  for (i = 0; i < Kc; ++i) grid[i] = h * (double) (i + 1);
  if (sf_integrate(L, t0, x, Kc, grid, X, xp, 1, &nsteps)) return 1;
  memcpy(L->chunk, L->stats, sizeof L->chunk);      /* the run counts this integration only */
  s = sf_density(nsteps, Kc, BM);
  if (*sub > s) s = *sub;
  used = s;
  hs = h / (double) s;
  /* the samples inside output steps 2..Kc (from the kept steps), then those of the first (its own integration) */
  nb = s > 1 ? (long) (Kc - 1) * (s - 1) + (s - 1) : 0;
  tb = sf_need(&w->tb, (size_t) nb + 1);
  Xb = 0;
  if (!tb) return -1;
  tc = t_out + row;
  for (i = 0; i < Kc; ++i) tc[i] = t0 + h * (double) (i + 1);
  if ((sf_cint) k + Kc == L->ints[I_M] && tc[Kc - 1] > L->reals[R_TF]) tc[Kc - 1] = L->reals[R_TF];
  if (s > 1) {
    long nin = (long) (Kc - 1) * (s - 1), nfirst = 0;
    double *rel = sf_need(&w->rel, (size_t) nin + 1);
    double *X1 = sf_need(&w->X1, (size_t) s * nx), *g1 = sf_need(&w->g1, (size_t) s);
    int first_ok;
    if (!rel || !X1 || !g1) return -1;
    for (i = 0; i + 1 < Kc; ++i)
      for (j = 1; j < s; ++j) rel[(size_t) i * (s - 1) + (j - 1)] = h * (double) (i + 1) + (double) j * hs;
    /* the first output step's own integration, before the sampling (it leaves the chunk's kept steps alone): how
     * many samples it gives is then known, and so every sample's place in time order */
    for (i = 0; i < s; ++i) g1[i] = hs * (double) (i + 1);
    first_ok = sf_integrate(L, t0, x, s, g1, X1, xp, 0, 0) == 0;
    if (L->ints[I_IN_PLACE] && nin > 0) {
      /* tb's times, the stable sort of [tc; tb] as below, then the kept steps' samples written by sf_sample_rows
       * straight into their rows of Xa = [x; samples in time order]: the values of the path below, one copy less */
      long a, *rows, *tmp;
      double *key;
      nfirst = first_ok ? s - 1 : 0;
      nb = nfirst + nin;
      Ta = Kc + nb;
      tb = sf_need(&w->tb, (size_t) nb + 1);
      ta = sf_need(&w->ta, (size_t) Ta + 1);
      order = (long *) (void *) sf_need(&w->order, (size_t) Ta + 1);
      rows = (long *) (void *) sf_need(&w->rows, (size_t) Ta + 1);
      Xa = sf_need(&w->Xa, ((size_t) Ta + 1) * nx);
      key = sf_need(&w->tg, (size_t) Ta + 1);
      tmp = (long *) (void *) sf_need(&w->Xr, (size_t) Ta + 1);
      if (!tb || !ta || !order || !rows || !Xa || !key || !tmp) return -1;
      for (j = 1; j <= nfirst; ++j) tb[j - 1] = t0 + hs * (double) j;
      for (i = 0; i < nin; ++i) tb[nfirst + i] = t0 + rel[i];
      for (a = 0; a < Ta; ++a) { key[a] = a < Kc ? tc[a] : tb[a - Kc]; order[a] = a; }
      sf_stable_sort(key, order, tmp, Ta);
      for (a = 0; a < Ta; ++a) { ta[a] = key[order[a]]; rows[order[a]] = a + 1; }
      {
        double c0 = sf_now();
        int rc = sf_sample_rows(L->cv, (int) nin, rel, Xa, rows + Kc + nfirst);
        L->integ += sf_now() - c0;
        if (rc == 0) {
          if (!first_ok) ++*unchecked;
          memcpy(Xa, x, (size_t) nx * sizeof(double));
          for (a = 0; a < Kc; ++a) memcpy(Xa + (size_t) rows[a] * nx, X + (size_t) a * nx, (size_t) nx * sizeof(double));
          for (a = 0; a < nfirst; ++a)
            memcpy(Xa + (size_t) rows[Kc + a] * nx, X1 + (size_t) a * nx, (size_t) nx * sizeof(double));
          O = sf_need(&w->O, ((size_t) Ta + 1) * L->nnz_all);
          if (!O) return -1;
          goto placed;
        }
      }
      nfirst = 0;                        /* the kept steps did not fit: the path below */
    }
    /* Xb: [the first step's s - 1 samples; the nin others], allocated only here: the in-place path above never
     * writes it, and a buffer it left unwritten was handed out written by the next run (480 pages faulted in
     * once per process: the in-place path's first fault count after a warm-up run, tests/test_heap.py) */
    Xb = sf_need(&w->Xb, ((size_t) nin + (size_t) s) * nx);
    if (!Xb) return -1;
    if (nin > 0) {
      double c0 = sf_now();
      int rc = sf_sample(L->cv, (int) nin, rel, Xb + (size_t) (s - 1) * nx);
      L->integ += sf_now() - c0;
      if (rc) {                          /* the kept steps did not fit in memory: the chunk integrated again on */
        long nd = (long) Kc * s - (s - 1), d;   /* the dense grid (Runner.grid(Kc, h, s)), its inner points kept */
        double *gd = sf_need(&w->tg, (size_t) nd), *Xd = sf_need(&w->Xg, (size_t) nd * nx);
        if (!gd || !Xd) return -1;
        for (i = 0, d = 0; i < Kc; ++i) {
          gd[d++] = h * (double) (i + 1);
          for (j = 1; j < s && i + 1 < Kc; ++j) gd[d++] = rel[(size_t) i * (s - 1) + (j - 1)];
        }
        if (sf_integrate(L, t0, x, (int) nd, gd, Xd, xp, 0, 0)) { nb = 0; goto sorted; }
        for (d = 0, i = 0; d < nd; ++d)
          if (d % s) memcpy(Xb + (size_t) (s - 1 + i++) * nx, Xd + (size_t) d * nx, (size_t) nx * sizeof(double));
      }
    }
    if (first_ok) nfirst = s - 1;
    else ++*unchecked;
    /* tb: [t1 (nfirst); t0 + rel]; Xb: [X1[:-1]; Y] */
    if (nfirst == 0) memmove(Xb, Xb + (size_t) (s - 1) * nx, (size_t) nin * nx * sizeof(double));
    else memcpy(Xb, X1, (size_t) (s - 1) * nx * sizeof(double));
    for (j = 1; j <= nfirst; ++j) tb[j - 1] = t0 + hs * (double) j;
    for (i = 0; i < nin; ++i) tb[nfirst + i] = t0 + rel[i];
    nb = nfirst + nin;
  } else {
    nb = 0;
  }
sorted:
  /* every sample in time order (a stable sort of [tc; tb]) copied into Xa: the path where the samples were not
   * written in place (ints[I_IN_PLACE] 0, the kept steps did not fit, or a chunk of one output step) */
  Ta = Kc + nb;
  ta = sf_need(&w->ta, (size_t) Ta + 1);
  order = (long *) (void *) sf_need(&w->order, (size_t) Ta + 1);
  Xa = sf_need(&w->Xa, ((size_t) Ta + 1) * nx);
  O = sf_need(&w->O, ((size_t) Ta + 1) * L->nnz_all);
  if (!ta || !order || !Xa || !O) return -1;
  {
    double *key = sf_need(&w->tg, (size_t) Ta + 1);
    long a;
    if (!key) return -1;
    long *tmp = (long *) (void *) sf_need(&w->Xr, (size_t) Ta + 1);
    if (!tmp) return -1;
    for (a = 0; a < Ta; ++a) { key[a] = a < Kc ? tc[a] : tb[a - Kc]; order[a] = a; }
    sf_stable_sort(key, order, tmp, Ta);
    memcpy(Xa, x, (size_t) nx * sizeof(double));          /* Xg = [x; samples in time order]; Xa = Xg + nx */
    for (a = 0; a < Ta; ++a) {
      long o = order[a];
      ta[a] = key[o];
      memcpy(Xa + (size_t) (a + 1) * nx, o < Kc ? X + (size_t) o * nx : Xb + (size_t) (o - Kc) * nx,
             (size_t) nx * sizeof(double));
    }
  }
placed:
  if (sf_outputs(L, Ta, ta, Xa + nx, O)) return 1;
  bi = sf_bad_index(L, O, Ta, Xa + nx);
  if (bi >= 0) return 1;
  /* _refine_chunk */
  samp = sf_need(&w->samp, (size_t) Ta + 1);
  if (!samp) return -1;
  {
    const double *m1 = sf_out(L, O, Ta, L->ints[I_IM1]), *m2 = sf_out(L, O, Ta, L->ints[I_IM2]);
    double start_m, *tg, lowest_now = *lowest, samp_min;
    int S = L->ints[I_SCAN_POINTS], width = 2 * n, rc, nsteps_set = 0, MR = L->ints[I_MAX_REFINED];
    long a, iw = 0, dips[64], ndips = 0, steps_set[130];
    sf_cint G;
    for (a = 0; a < Ta; ++a) {
      double v1 = m1[a], v2 = m2[a];
      for (c = 1; c < n; ++c) {
        v1 = sf_npmin(v1, m1[(size_t) c * Ta + a]);
        v2 = sf_npmin(v2, m2[(size_t) c * Ta + a]);
      }
      samp[a] = sf_fmin(v1, v2);
    }
    /* the start's margins: one scan-function evaluation */
    {
      const double *in[4];
      double *out[1], mstart[256], tt = t0;
      double qq[128], dd[128];
      if (width > 256 || n > 128) return 1;
      for (c = 0; c < n; ++c) { qq[c] = x[L->ints[I_Q0] + c]; dd[c] = x[L->ints[I_DQ0] + c]; }
      in[0] = &tt; in[1] = qq; in[2] = dd; in[3] = L->pvals;
      out[0] = mstart;
      if (L->margins(1, in, out)) return 1;
      start_m = mstart[0];
      for (c = 1; c < width; ++c) start_m = sf_npmin(start_m, mstart[c]);
    }
    tg = sf_need(&w->tb, (size_t) Ta + 1);       /* [t0; ta] (tb is no longer needed) */
    if (!tg) return -1;
    tg[0] = t0;
    memcpy(tg + 1, ta, (size_t) Ta * sizeof(double));
    rc = sf_scan(L, Ta + 1, tg, Xa, &w->tsc, &w->Qsc, &w->DQsc, &w->Msc);
    if (rc) return rc < 0 ? -1 : 1;
    G = (sf_cint) Ta * (S - 1);
    /* scan_dips: gaps whose scan goes to 0 or SCAN_DIP below both ends, deepest first (stable), MAX_REFINED */
    {
      double *mn = sf_need(&w->Qsc, (size_t) Ta + 1);    /* (the scan's inputs are no longer needed) */
      if (!mn) return -1;
      for (a = 0; a < Ta; ++a) {
        double v = INFINITY, ends, e0 = a == 0 ? start_m : samp[a - 1];
        int jj;
        for (jj = 0; jj < S - 1; ++jj)
          for (c = 0; c < width; ++c) {
            double y = w->Msc.v[(size_t) c * G + (sf_cint) a * (S - 1) + jj];
            if (!isfinite(y)) y = -INFINITY;
            if (y < v) v = y;
          }
        mn[a] = v;
        ends = sf_fmin(e0, samp[a]);
        if (v <= 0 || v < ends - L->reals[R_SCAN_DIP]) {
          long b2;                                         /* insert by mn, stably, keeping the MR smallest */
          if (ndips < MR) dips[ndips++] = a;
          else if (v < mn[dips[MR - 1]]) dips[MR - 1] = a;
          else continue;
          for (b2 = ndips - 1; b2 > 0 && mn[dips[b2 - 1]] > mn[dips[b2]]; --b2) {
            long tmp = dips[b2]; dips[b2] = dips[b2 - 1]; dips[b2 - 1] = tmp;
          }
        }
      }
      if (MR > 64) return 1;
    }
    {
      double best = INFINITY;
      iw = 0;
      for (a = 0; a < Ta; ++a) {
        double v = isfinite(samp[a]) ? samp[a] : INFINITY;
        if (v < best) { best = v; iw = a; }
      }
      if (Ta > 0 && samp[iw] < lowest_now + L->reals[R_SCAN_DIP]) {
        long kw = sf_left(tc, Kc, ta[iw]);
        steps_set[nsteps_set++] = kw;
        if (order[iw] < Kc) steps_set[nsteps_set++] = kw + 1;
      }
      for (a = 0; a < ndips; ++a) steps_set[nsteps_set++] = sf_left(tc, Kc, ta[dips[a]]);
    }
    /* sorted, distinct, < Kc */
    {
      int u, v2;
      for (u = 1; u < nsteps_set; ++u)
        for (v2 = u; v2 > 0 && steps_set[v2 - 1] > steps_set[v2]; --v2) {
          long tmp = steps_set[v2]; steps_set[v2] = steps_set[v2 - 1]; steps_set[v2 - 1] = tmp;
        }
      for (u = 0; u < nsteps_set; ++u) {
        long qs = steps_set[u];
        double t_a;
        const double *x_a;
        if ((u > 0 && qs == steps_set[u - 1]) || qs >= Kc) continue;
        t_a = qs == 0 ? t0 : tc[qs - 1];
        x_a = qs == 0 ? x : X + (size_t) (qs - 1) * nx;
        rc = sf_refine(L, w, B, t_a, x_a, tc[qs] - t_a);
        if (rc) return rc;
      }
    }
    /* lowest = min(lowest, the chunk's smallest sampled margin, the smallest between so far) */
    samp_min = NAN;
    for (a = 0; a < Ta; ++a) if (!isnan(samp[a]) && (isnan(samp_min) || samp[a] < samp_min)) samp_min = samp[a];
    {
      double bmin = NAN, lo = lowest_now;
      for (c = 0; c < n; ++c) {
        double v = sf_fmin(B->m1[c], B->m2[c]);
        if (!isnan(v) && (isnan(bmin) || v < bmin)) bmin = v;
      }
      if (samp_min < lo) lo = samp_min;
      if (bmin < lo) lo = bmin;
      *lowest = lo;
    }
  }
  /* the samples between output points, in time order, into Between; the output points into the run's arrays */
  {
    long a, r;
    sf_between_update(L, B, ta, O, Ta, order, Kc, used);
    /* the output points: states and logged signals into the run's arrays at `row` */
    for (a = 0; a < Ta; ++a) {
      if (order[a] >= Kc) continue;
      r = row + order[a];
      memcpy(X_out + (size_t) r * nx, X + (size_t) order[a] * nx, (size_t) nx * sizeof(double));
      {
        size_t off = 0, offr = 0;
        int o;
        for (o = 0; o < L->nout; ++o) {
          for (c = 0; c < L->nnz_out[o]; ++c) O_out[offr + (size_t) c * rows + r] = O[off + (size_t) c * Ta + a];
          off += (size_t) Ta * L->nnz_out[o];
          offr += (size_t) rows * L->nnz_out[o];
        }
      }
    }
  }
  Kn = sf_density(nsteps, Kc, BM);
  *sub = Kn;
  return 0;
}

/* The run from state[S_K] to ints[I_M] output points, or until a chunk is handed over, the time slice is used or the
 * wall-clock limit is reached. handle: the CVODES driver; outputs / margins: the closed loop's `_many` functions;
 * ints / reals: the settings (enums above); perm: integrator state i = public state perm[i]; nnz_out: each logged
 * signal's size; chunks: CHUNK_SIZES (ints[I_NCHUNK]); pvals: [plant p; z]; x (nx, public order, in and out);
 * state (S_NSTATE, in and out) and fstate[0] = the smallest margin so far (in and out), fstate[1] += the seconds
 * inside CVODES; between: m1, m2, t_m1, t_m2, tau, t_tau, tau_applied (n each, in and out); stats (4: steps, rhs
 * evaluations, Jacobian evaluations, error-test failures, added to); t_out (rows), X_out (rows x nx), O_out (the
 * logged signals, each rows x nnz column-major, one after another): the output points from row 0 on, for the
 * output points k_start + 1 .. ; state[S_DONE] = rows written. Returns SF_LOOP_*. */
int sf_loop_run(void *handle, void *outputs, void *margins, const int *ints, const double *reals, const int *perm,
                const int *nnz_out, const int *chunks, const double *pvals, double *x, long *state, double *fstate,
                double *between, long *stats, double *t_out, double *X_out, double *O_out, long rows) {
  sf_loop L;
  sf_work w;
  sf_between B, Bkeep;
  double *bkeep = 0, start = sf_now();
  int i, rc = SF_LOOP_DONE, n = ints[I_N], nx = ints[I_NX];
  long k = state[S_K], K = state[S_KC], M = ints[I_M], row = state[S_DONE];
  int sub = (int) state[S_SUB];
  long unchecked = state[S_UNCHECKED];
  memset(&L, 0, sizeof L);
  memset(&w, 0, sizeof w);
  L.cv = handle;
  memcpy(&L.outputs, &outputs, sizeof L.outputs);
  memcpy(&L.margins, &margins, sizeof L.margins);
  L.ints = ints; L.reals = reals; L.perm = perm; L.nnz_out = nnz_out; L.chunks = chunks; L.pvals = pvals;
  L.nx = nx; L.n = n; L.np = ints[I_NP]; L.nout = ints[I_NOUT];
  for (i = 0; i < L.nout; ++i) L.nnz_all += nnz_out[i];
  L.p = malloc((size_t) L.np * sizeof(double));
  bkeep = malloc((size_t) 7 * n * sizeof(double));
  if (!L.p || !bkeep) { free(L.p); free(bkeep); return SF_LOOP_NOMEM; }
  B.m1 = between; B.m2 = between + n; B.t_m1 = between + 2 * n; B.t_m2 = between + 3 * n; B.tau = between + 4 * n;
  B.t_tau = between + 5 * n; B.tau_applied = between + 6 * n;
  B.points = state[S_POINTS]; B.density = state[S_DENSITY]; B.refined = state[S_REFINED];
  while (k < M) {
    double c0 = sf_now(), elapsed = reals[R_ELAPSED0] + (c0 - start), lowest = fstate[0], spent, per_point,
        remaining;
    int Kc = (int) (K < M - k ? K : M - k), sub_new = sub, r;
    long unch = unchecked;
    if (elapsed > reals[R_LIMIT]) { rc = SF_LOOP_TIMEOUT; break; }
    if (c0 - start > reals[R_SLICE]) { rc = SF_LOOP_SLICE; break; }
    if (row + Kc > rows) { rc = SF_LOOP_HANDOVER; break; }
    memcpy(bkeep, between, (size_t) 7 * n * sizeof(double));
    Bkeep = B;
    r = sf_chunk(&L, &w, k, Kc, x, &B, &lowest, &sub_new, &unch, t_out, X_out, O_out, rows, row);
    if (r) {                                  /* nothing of the chunk is kept */
      memcpy(between, bkeep, (size_t) 7 * n * sizeof(double));
      B = Bkeep;
      rc = r < 0 ? SF_LOOP_NOMEM : SF_LOOP_HANDOVER;
      break;
    }
    stats[0] += L.chunk[0]; stats[1] += L.chunk[1]; stats[2] += L.chunk[6]; stats[3] += L.chunk[3];
    fstate[0] = lowest;
    sub = sub_new;
    unchecked = unch;
    memcpy(x, X_out + (size_t) (row + Kc - 1) * nx, (size_t) nx * sizeof(double));
    k += Kc;
    row += Kc;
    /* the next chunk's length: CHUNK_SIZES onwards, shrunk only where it would overrun the wall-clock limit */
    spent = sf_now() - c0;
    per_point = spent / (double) Kc;
    remaining = reals[R_LIMIT] - (reals[R_ELAPSED0] + (sf_now() - start));
    if (remaining < 1e-3) remaining = 1e-3;
    {
      int nc = ints[I_NCHUNK], idx = -1, best = -1;
      for (i = 0; i < nc; ++i) if (chunks[i] == K) idx = i;
      if (ints[I_FIXED]) K = chunks[nc - 1];
      else K = idx < 0 ? 1 : chunks[idx + 1 < nc ? idx + 1 : nc - 1];
      if (per_point * (double) K > remaining / 4) {
        for (i = 0; i < nc; ++i)
          if (per_point * (double) chunks[i] <= remaining / 4 && chunks[i] > best) best = chunks[i];
        K = best > 0 ? best : 1;
      }
    }
  }
  state[S_K] = k; state[S_KC] = K; state[S_SUB] = sub; state[S_POINTS] = B.points; state[S_DENSITY] = B.density;
  state[S_REFINED] = B.refined; state[S_UNCHECKED] = unchecked; state[S_DONE] = row;
  fstate[1] += L.integ;
  free(L.p);
  free(bkeep);
  sf_work_free(&w);
  return rc;
}
