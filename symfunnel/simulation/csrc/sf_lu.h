/* The Newton matrix's LU for symfunnel's CVODES driver (included by cvodes_driver.c): A = I - gamma J on J's fixed
 * sparsity pattern, diagonal pivots, the fill computed once.
 *
 * Two numeric factorisations of the same symbolic analysis, bit for bit the same factors: sf_lu_factor_columns, a
 * left-looking LU through a dense work column (each column scattered into it, eliminated, gathered back), and
 * sf_lu_factor (the default), the same operations in the same order on the factors' own storage: the analysis
 * lists, for every update of the elimination, the position of the entry it changes (udst), so a factorisation is
 * straight passes over index arrays, without the scatter and gather (paper's loop: 1,251 factorisations per 20 s
 * run, a tenth of the run in the column form). */
#ifndef SF_LU_H
#define SF_LU_H

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define SF_GROWTH_MAX 1e8       /* largest entry of the eliminated matrix / largest entry of A (Wilkinson growth) */

/* ---- LU of A = I - gamma J on a fixed pattern, diagonal pivots ------------------------------------------- */

typedef struct {
  int n;
  int *Ap, *Ai, *jmap, *dmap;    /* A's pattern (CSC, the diagonal included); J nonzero k -> A entry jmap[k] */
  double *Ax;
  int *Lp, *Li, *Up, *Ui;        /* L strictly below the diagonal; U with each column's diagonal last */
  double *Lx, *Ux, *x;           /* x: dense work vector, zero between uses; Lx = Ux + nu (one block) */
  double max_growth;             /* largest growth factor of a factorisation so far (statistics) */
  int nu, nl, nupd;              /* entries of U and of L; updates of the elimination */
  int *jdst, *udst;              /* J nonzero k -> its entry of [Ux; Lx]; update t -> the entry it changes */
  int columns;                   /* 1: factorise with sf_lu_factor_columns and solve by columns (the reference) */
  /* the factors by rows, for the solve: L's row i ascending by column, U's strictly upper row i descending by
   * column (Rl*, Ru*: row pointers, columns, positions in Lx / Ux), their values copied after each factorisation */
  int *Rlp, *Rlj, *Rlpos, *Rup, *Ruj, *Rupos;
  double *RLx, *RUx, *Rd;
} sf_lu;

static void sf_lu_free(sf_lu *f) {
  free(f->Ap); free(f->Ai); free(f->jmap); free(f->dmap); free(f->Ax);
  free(f->Lp); free(f->Li); free(f->Up); free(f->Ui); free(f->Ux); free(f->x); free(f->jdst); free(f->udst);
  free(f->Rlp); free(f->Rlj); free(f->Rlpos); free(f->Rup); free(f->Ruj); free(f->Rupos);
  free(f->RLx); free(f->RUx); free(f->Rd);
  memset(f, 0, sizeof *f);
}

/* Symbolic analysis, once: A's pattern from J's (CSC colind Jp, rows Ji) plus the diagonal, then the fill of L and
 * U column by column (no pivoting: column j's pattern is A's column closed under the L columns k < j it hits). */
static int sf_lu_schedule(sf_lu *f, const int *Jp, const int *Ji);
static int sf_lu_rows(sf_lu *f);

static int sf_lu_analyse(sf_lu *f, int n, const int *Jp, const int *Ji) {
  int j, p, k, i, nnzA = 0, nl = 0, nu = 0, capl, capu;
  char *mark;
  int *list;
  memset(f, 0, sizeof *f);
  f->n = n;
  f->max_growth = 0.0;
  f->Ap = malloc((size_t) (n + 1) * sizeof(int));
  f->Ai = malloc((size_t) (Jp[n] + n) * sizeof(int));
  f->jmap = malloc((size_t) (Jp[n] > 0 ? Jp[n] : 1) * sizeof(int));
  f->dmap = malloc((size_t) n * sizeof(int));
  f->x = calloc((size_t) n, sizeof(double));
  f->Lp = malloc((size_t) (n + 1) * sizeof(int));
  f->Up = malloc((size_t) (n + 1) * sizeof(int));
  mark = calloc((size_t) n, 1);
  list = malloc((size_t) n * sizeof(int));
  capl = capu = Jp[n] + n + 16;
  f->Li = malloc((size_t) capl * sizeof(int));
  f->Ui = malloc((size_t) capu * sizeof(int));
  if (!f->Ap || !f->Ai || !f->jmap || !f->dmap || !f->x || !f->Lp || !f->Up || !mark || !list || !f->Li || !f->Ui)
    goto fail;
  for (j = 0; j < n; ++j) {                         /* A = J + diagonal, rows ascending within a column */
    int diag_done = 0;
    f->Ap[j] = nnzA;
    for (p = Jp[j]; p < Jp[j + 1]; ++p) {
      if (p > Jp[j] && Ji[p] <= Ji[p - 1]) goto fail;          /* rows must be sorted (CasADi's are) */
      if (!diag_done && Ji[p] > j) { f->dmap[j] = nnzA; f->Ai[nnzA++] = j; diag_done = 1; }
      if (Ji[p] == j) { f->dmap[j] = nnzA; diag_done = 1; }
      f->jmap[p] = nnzA;
      f->Ai[nnzA++] = Ji[p];
    }
    if (!diag_done) { f->dmap[j] = nnzA; f->Ai[nnzA++] = j; }
  }
  f->Ap[n] = nnzA;
  f->Ax = malloc((size_t) nnzA * sizeof(double));
  if (!f->Ax) goto fail;
  for (j = 0; j < n; ++j) {                         /* fill: column j of L + U */
    int m = 0;
    for (p = f->Ap[j]; p < f->Ap[j + 1]; ++p) mark[f->Ai[p]] = 1;
    for (k = 0; k < j; ++k) {                       /* ascending k: every update of x[k] comes from an m < k */
      if (!mark[k]) continue;
      for (p = f->Lp[k]; p < f->Lp[k + 1]; ++p) mark[f->Li[p]] = 1;
    }
    for (i = 0; i < n; ++i)
      if (mark[i]) { list[m++] = i; mark[i] = 0; }
    f->Up[j] = nu;
    f->Lp[j] = nl;
    for (k = 0; k < m; ++k) {
      i = list[k];
      if (i <= j) {
        if (nu == capu) { capu *= 2; f->Ui = realloc(f->Ui, (size_t) capu * sizeof(int)); if (!f->Ui) goto fail; }
        f->Ui[nu++] = i;                            /* ascending, so the diagonal (i = j) comes last */
      } else {
        if (nl == capl) { capl *= 2; f->Li = realloc(f->Li, (size_t) capl * sizeof(int)); if (!f->Li) goto fail; }
        f->Li[nl++] = i;
      }
    }
    f->Lp[j + 1] = nl;                              /* read by later columns' fill */
    if (nu == f->Up[j] || f->Ui[nu - 1] != j) goto fail;
  }
  f->Up[n] = nu;
  f->nu = nu;
  f->nl = nl;
  f->Ux = malloc((size_t) (nu + nl) * sizeof(double));
  if (!f->Ux) goto fail;
  f->Lx = f->Ux + nu;
  free(mark);
  free(list);
  return sf_lu_schedule(f, Jp, Ji);
fail:
  free(mark);
  free(list);
  sf_lu_free(f);
  return -1;
}

/* A = I - gamma J from J's nonzeros, then the numeric factorisation through the dense work column x; 1 on a zero
 * or non-finite pivot or too much growth. */
static int sf_lu_factor_columns(sf_lu *f, const double *Jx, int nnzJ, double gamma) {
  int n = f->n, j, p, q, k;
  double *x = f->x, amax = 0.0, gmax = 0.0;
  memset(f->Ax, 0, (size_t) f->Ap[n] * sizeof(double));
  for (k = 0; k < nnzJ; ++k) f->Ax[f->jmap[k]] = -gamma * Jx[k];
  for (j = 0; j < n; ++j) f->Ax[f->dmap[j]] += 1.0;
  for (p = 0; p < f->Ap[n]; ++p)
    if (fabs(f->Ax[p]) > amax) amax = fabs(f->Ax[p]);
  for (j = 0; j < n; ++j) {
    double piv;
    for (p = f->Ap[j]; p < f->Ap[j + 1]; ++p) x[f->Ai[p]] = f->Ax[p];
    for (p = f->Up[j]; p < f->Up[j + 1] - 1; ++p) {  /* U entries above the diagonal, ascending row */
      double xk;
      k = f->Ui[p];
      xk = x[k];
      for (q = f->Lp[k]; q < f->Lp[k + 1]; ++q) x[f->Li[q]] -= f->Lx[q] * xk;
    }
    for (p = f->Up[j]; p < f->Up[j + 1]; ++p) {
      f->Ux[p] = x[f->Ui[p]];
      x[f->Ui[p]] = 0.0;
      if (fabs(f->Ux[p]) > gmax) gmax = fabs(f->Ux[p]);
    }
    for (p = f->Lp[j]; p < f->Lp[j + 1]; ++p)
      if (fabs(x[f->Li[p]]) > gmax) gmax = fabs(x[f->Li[p]]);
    piv = f->Ux[f->Up[j + 1] - 1];
    if (piv == 0.0 || !isfinite(piv) || !(gmax <= SF_GROWTH_MAX * amax)) {
      for (p = f->Lp[j]; p < f->Lp[j + 1]; ++p) x[f->Li[p]] = 0.0;
      return 1;
    }
    for (p = f->Lp[j]; p < f->Lp[j + 1]; ++p) { f->Lx[p] = x[f->Li[p]] / piv; x[f->Li[p]] = 0.0; }
  }
  if (amax > 0.0 && gmax / amax > f->max_growth) f->max_growth = gmax / amax;
  return 0;
}

/* Where each J nonzero and each update of the elimination lands in [Ux; Lx] (sf_lu_factor's schedule): column j's
 * updates in sf_lu_factor_columns' order (its U entries above the diagonal by ascending row k, then L column k's
 * rows). 0, or -1 (out of memory, or an update outside the pattern: the fill analysis would be wrong). */
static int sf_lu_schedule(sf_lu *f, const int *Jp, const int *Ji) {
  int n = f->n, j, p, q, t = 0, *where = malloc((size_t) n * sizeof(int));
  f->nupd = 0;
  for (j = 0; j < n; ++j)
    for (p = f->Up[j]; p < f->Up[j + 1] - 1; ++p) f->nupd += f->Lp[f->Ui[p] + 1] - f->Lp[f->Ui[p]];
  f->udst = malloc((size_t) (f->nupd > 0 ? f->nupd : 1) * sizeof(int));
  f->jdst = malloc((size_t) (Jp[n] > 0 ? Jp[n] : 1) * sizeof(int));
  if (!where || !f->udst || !f->jdst) { free(where); return -1; }
  for (j = 0; j < n; ++j) where[j] = -1;
  for (j = 0; j < n; ++j) {
    for (p = f->Up[j]; p < f->Up[j + 1]; ++p) where[f->Ui[p]] = p;
    for (p = f->Lp[j]; p < f->Lp[j + 1]; ++p) where[f->Li[p]] = f->nu + p;
    for (p = Jp[j]; p < Jp[j + 1]; ++p) f->jdst[p] = where[Ji[p]];
    for (p = f->Up[j]; p < f->Up[j + 1] - 1; ++p) {
      int k = f->Ui[p];
      for (q = f->Lp[k]; q < f->Lp[k + 1]; ++q) {
        if (where[f->Li[q]] < 0) { free(where); return -1; }
        f->udst[t++] = where[f->Li[q]];
      }
    }
    for (p = f->Up[j]; p < f->Up[j + 1]; ++p) where[f->Ui[p]] = -1;
    for (p = f->Lp[j]; p < f->Lp[j + 1]; ++p) where[f->Li[p]] = -1;
  }
  free(where);
  return sf_lu_rows(f);
}

/* The row-wise index of L and of U's strict upper part (sf_lu_solve's order). 0, or -1 (out of memory). */
static int sf_lu_rows(sf_lu *f) {
  int n = f->n, j, p, i, nus = f->nu - n, *cl, *cu;
  f->Rlp = calloc((size_t) n + 1, sizeof(int));
  f->Rup = calloc((size_t) n + 1, sizeof(int));
  f->Rlj = malloc((size_t) (f->nl > 0 ? f->nl : 1) * sizeof(int));
  f->Rlpos = malloc((size_t) (f->nl > 0 ? f->nl : 1) * sizeof(int));
  f->Ruj = malloc((size_t) (nus > 0 ? nus : 1) * sizeof(int));
  f->Rupos = malloc((size_t) (nus > 0 ? nus : 1) * sizeof(int));
  f->RLx = malloc((size_t) (f->nl > 0 ? f->nl : 1) * sizeof(double));
  f->RUx = malloc((size_t) (nus > 0 ? nus : 1) * sizeof(double));
  f->Rd = malloc((size_t) n * sizeof(double));
  cl = calloc((size_t) n + 1, sizeof(int));
  cu = calloc((size_t) n + 1, sizeof(int));
  if (!f->Rlp || !f->Rup || !f->Rlj || !f->Rlpos || !f->Ruj || !f->Rupos || !f->RLx || !f->RUx || !f->Rd || !cl
      || !cu) { free(cl); free(cu); return -1; }
  for (p = 0; p < f->nl; ++p) f->Rlp[f->Li[p] + 1]++;
  for (j = 0; j < n; ++j)
    for (p = f->Up[j]; p < f->Up[j + 1] - 1; ++p) f->Rup[f->Ui[p] + 1]++;
  for (i = 0; i < n; ++i) { f->Rlp[i + 1] += f->Rlp[i]; f->Rup[i + 1] += f->Rup[i]; }
  memcpy(cl, f->Rlp, (size_t) (n + 1) * sizeof(int));
  memcpy(cu, f->Rup, (size_t) (n + 1) * sizeof(int));
  for (j = 0; j < n; ++j)                           /* ascending columns: each L row ascending */
    for (p = f->Lp[j]; p < f->Lp[j + 1]; ++p) { f->Rlj[cl[f->Li[p]]] = j; f->Rlpos[cl[f->Li[p]]++] = p; }
  for (j = n - 1; j >= 0; --j)                      /* descending columns: each U row descending */
    for (p = f->Up[j]; p < f->Up[j + 1] - 1; ++p) { f->Ruj[cu[f->Ui[p]]] = j; f->Rupos[cu[f->Ui[p]]++] = p; }
  free(cl);
  free(cu);
  return 0;
}

/* The factors' values in the row-wise order (after each factorisation). */
static void sf_lu_copy_rows(sf_lu *f) {
  int k, nus = f->nu - f->n;
  for (k = 0; k < f->nl; ++k) f->RLx[k] = f->Lx[f->Rlpos[k]];
  for (k = 0; k < nus; ++k) f->RUx[k] = f->Ux[f->Rupos[k]];
  for (k = 0; k < f->n; ++k) f->Rd[k] = f->Ux[f->Up[k + 1] - 1];
}

/* sf_lu_factor_columns' factorisation (the same operations on the same values in the same order, so the same
 * factors and the same refusals), on [Ux; Lx] directly along the schedule. */
static int sf_lu_factor(sf_lu *f, const double *Jx, int nnzJ, double gamma) {
  int n = f->n, j, p, q, k, t = 0, nv = f->nu + f->nl, fail = 0;
  const int *udst = f->udst, *Lp = f->Lp;
  double *V = f->Ux, *Lx = f->Lx, amax, gmax, m[4] = {0.0, 0.0, 0.0, 0.0}, g[4] = {0.0, 0.0, 0.0, 0.0};
  if (f->columns) return sf_lu_factor_columns(f, Jx, nnzJ, gamma);
  memset(V, 0, (size_t) nv * sizeof(double));       /* fill entries, and diagonal ones J leaves out, start at 0 */
  for (k = 0; k < nnzJ; ++k) V[f->jdst[k]] = -gamma * Jx[k];
  for (j = 0; j < n; ++j) V[f->Up[j + 1] - 1] += 1.0;
  /* the largest |entry| of A (the fill entries are 0 here) and, below, of the eliminated columns: maxima are
   * exact whatever the order, so four independent running maxima (NaN skipped by each, as by one) */
  for (p = 0; p + 4 <= nv; p += 4)
    for (q = 0; q < 4; ++q)
      if (fabs(V[p + q]) > m[q]) m[q] = fabs(V[p + q]);
  for (; p < nv; ++p)
    if (fabs(V[p]) > m[0]) m[0] = fabs(V[p]);
  amax = fmax(fmax(m[0], m[1]), fmax(m[2], m[3]));
  for (j = 0; j < n && !fail; ++j) {
    int u1 = f->Up[j + 1], l0 = Lp[j], l1 = Lp[j + 1];
    double piv;
    for (p = f->Up[j]; p < u1 - 1; ++p) {           /* U entries above the diagonal, ascending row */
      double xk = V[p];
      k = f->Ui[p];
      for (q = Lp[k]; q < Lp[k + 1]; ++q) V[udst[t++]] -= Lx[q] * xk;
    }
    piv = V[u1 - 1];
    if (piv == 0.0 || !isfinite(piv)) fail = 1;
    for (p = l0; p < l1; ++p) {                      /* growth measured before the division, as the columns form */
      if (fabs(Lx[p]) > g[p & 3]) g[p & 3] = fabs(Lx[p]);
      Lx[p] /= piv;
    }
  }
  for (p = 0; p + 4 <= f->nu; p += 4)                /* U's entries are final once their column is done */
    for (q = 0; q < 4; ++q)
      if (fabs(V[p + q]) > g[q]) g[q] = fabs(V[p + q]);
  for (; p < f->nu; ++p)
    if (fabs(V[p]) > g[0]) g[0] = fabs(V[p]);
  gmax = fmax(fmax(g[0], g[1]), fmax(g[2], g[3]));
  /* the columns form stops at the first column failing either test; the growth test on the whole factor fails iff
   * it fails on some first columns (gmax only grows), so the answer is the same */
  if (fail || !(gmax <= SF_GROWTH_MAX * amax)) return 1;
  if (amax > 0.0 && gmax / amax > f->max_growth) f->max_growth = gmax / amax;
  sf_lu_copy_rows(f);
  return 0;
}

/* b <- A^-1 b with the last factorisation, column by column (the reference). */
static void sf_lu_solve_columns(const sf_lu *f, double *b) {
  int n = f->n, j, p;
  for (j = 0; j < n; ++j) {                         /* column by column, as CSparse's cs_lsolve and cs_usolve */
    double bj = b[j];
    for (p = f->Lp[j]; p < f->Lp[j + 1]; ++p) b[f->Li[p]] -= f->Lx[p] * bj;
  }
  for (j = n - 1; j >= 0; --j) {
    double bj = b[j] / f->Ux[f->Up[j + 1] - 1];
    b[j] = bj;
    for (p = f->Up[j]; p < f->Up[j + 1] - 1; ++p) b[f->Ui[p]] -= f->Ux[p] * bj;
  }
}

/* b <- A^-1 b with the last factorisation: row by row, each b[i] accumulated in a register instead of updated in
 * memory by every column (the same operations on each b[i] in the same order as sf_lu_solve_columns: L's columns
 * ascending, U's descending, then U's diagonal; so the same doubles). */
static void sf_lu_solve(const sf_lu *f, double *b) {
  int n = f->n, i, t;
  const int *Rlp = f->Rlp, *Rlj = f->Rlj, *Rup = f->Rup, *Ruj = f->Ruj;
  const double *RLx = f->RLx, *RUx = f->RUx;
  if (f->columns) { sf_lu_solve_columns(f, b); return; }
  for (i = 0; i < n; ++i) {
    double acc = b[i];
    for (t = Rlp[i]; t < Rlp[i + 1]; ++t) acc -= RLx[t] * b[Rlj[t]];
    b[i] = acc;
  }
  for (i = n - 1; i >= 0; --i) {
    double acc = b[i];
    for (t = Rup[i]; t < Rup[i + 1]; ++t) acc -= RUx[t] * b[Ruj[t]];
    b[i] = acc / f->Rd[i];
  }
}

#endif
