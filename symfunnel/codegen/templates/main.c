/* Example: run the generated funnel controller over a recorded trajectory.
 *
 *   make && ./symfunnel_main trajectory.txt
 *
 * Each line of the trajectory holds the controller's inputs in the order of manifest.json
 * (t, q, dq, qd, dqd, ddqd, x_esn, w_hat; matrices column-major); lines starting with '#' are comments.
 * For every line the program prints t and the torque tau, one line per sample.
 * It uses CasADi's C API of the generated code (incref, checkout, work sizes, call, release, decref)
 * and static memory only: no casadi, no malloc.
 */
#include <stdio.h>
#include "symfunnel_controller.h"

#define SZ(n) ((n) > 0 ? (n) : 1)
#ifndef MAX_VALUES
#define MAX_VALUES 65536
#endif

static casadi_real in_values[MAX_VALUES];
static casadi_real out_values[MAX_VALUES];
static const casadi_real *arg[SZ(controller_SZ_ARG)];
static casadi_real *res[SZ(controller_SZ_RES)];
static casadi_int iw[SZ(controller_SZ_IW)];
static casadi_real w[SZ(controller_SZ_W)];

/* Number of stored entries of a CasADi sparsity pattern (nrow, ncol, then 1 for dense, else colind, row). */
static casadi_int nnz(const casadi_int *sp) {
  casadi_int ncol = sp[1];
  if (ncol > 0 && sp[2] == 1) return sp[0] * ncol;
  return sp[2 + ncol];
}

/* Read the next number, skipping white space and '#' comment lines; 1 on success, 0 at end of file. */
static int read_number(FILE *fp, casadi_real *x) {
  int c;
  double v;
  for (;;) {
    c = fgetc(fp);
    if (c == EOF) return 0;
    if (c == '#') {
      while (c != '\n' && c != EOF) c = fgetc(fp);
      continue;
    }
    if (c == ' ' || c == '\t' || c == '\n' || c == '\r') continue;
    ungetc(c, fp);
    if (fscanf(fp, "%lf", &v) != 1) return -1;
    *x = (casadi_real) v;
    return 1;
  }
}

int main(int argc, char *argv[]) {
  const char *path = argc > 1 ? argv[1] : "trajectory.txt";
  casadi_int n_in = controller_n_in(), n_out = controller_n_out();
  casadi_int sz_arg, sz_res, sz_iw, sz_w, i, total_in = 0, total_out = 0;
  long row = 0;
  int mem, status = 0;
  FILE *fp;

  if (controller_work(&sz_arg, &sz_res, &sz_iw, &sz_w)) return 1;
  if (sz_arg > SZ(controller_SZ_ARG) || sz_res > SZ(controller_SZ_RES) || sz_iw > SZ(controller_SZ_IW)
      || sz_w > SZ(controller_SZ_W)) {
    fprintf(stderr, "work arrays too small\n");
    return 1;
  }
  for (i = 0; i < n_in; ++i) {
    arg[i] = in_values + total_in;
    total_in += nnz(controller_sparsity_in(i));
  }
  for (i = 0; i < n_out; ++i) {
    res[i] = out_values + total_out;
    total_out += nnz(controller_sparsity_out(i));
  }
  if (total_in > MAX_VALUES || total_out > MAX_VALUES) {
    fprintf(stderr, "increase MAX_VALUES to %ld\n", (long) (total_in > total_out ? total_in : total_out));
    return 1;
  }
  fp = fopen(path, "r");
  if (!fp) {
    fprintf(stderr, "cannot open %s\n", path);
    return 1;
  }
  controller_incref();
  mem = controller_checkout();
  printf("# t");
  for (i = 0; i < nnz(controller_sparsity_out(0)); ++i) printf(" %s%ld", controller_name_out(0), (long) (i + 1));
  printf("\n");
  for (;;) {
    int got = read_number(fp, &in_values[0]);
    if (got == 0) break;
    for (i = 1; got == 1 && i < total_in; ++i) got = read_number(fp, &in_values[i]);
    if (got != 1) {
      fprintf(stderr, "%s: row %ld: expected %ld numbers\n", path, row + 1, (long) total_in);
      status = 1;
      break;
    }
    if (controller(arg, res, iw, w, mem)) {
      fprintf(stderr, "row %ld: evaluation failed\n", row + 1);
      status = 1;
      break;
    }
    printf("%.17g", (double) in_values[0]);
    for (i = 0; i < nnz(controller_sparsity_out(0)); ++i) printf(" %.17g", (double) res[0][i]);
    printf("\n");
    ++row;
  }
  controller_release(mem);
  controller_decref();
  fclose(fp);
  if (!status && row == 0) {
    fprintf(stderr, "%s: no samples\n", path);
    status = 1;
  }
  return status;
}
