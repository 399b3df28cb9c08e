/* Time one call of the generated controller, in C: cycles over the samples of a recorded trajectory.
 *
 *   make bench && ./symfunnel_bench trajectory.txt [ITERATIONS]
 *
 * Prints "ns_per_call <value> iterations <n> checksum <sum of tau> step_ns_per_call <value>": the best of
 * several repetitions of one controller call, and of one @P@step call (t, q, dq of the samples; the state
 * restarts from @P@init every `rows` calls so that it stays near the recorded one), in CPU time of this thread
 * (what the calls cost, whatever else runs on the machine; the wall clock where that clock is missing).
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "@BASENAME@.h"

#define SZ(n) ((n) > 0 ? (n) : 1)
#ifndef MAX_VALUES
#define MAX_VALUES 65536
#endif
#ifndef MAX_IN
#define MAX_IN 4096
#endif
#ifndef MAX_ROWS
#define MAX_ROWS 16
#endif

static casadi_real in_values[MAX_ROWS][MAX_IN];
static casadi_real out_values[MAX_VALUES];
static const casadi_real *arg[MAX_ROWS][SZ(@F@controller_SZ_ARG)];
static casadi_real *res[SZ(@F@controller_SZ_RES)];
static casadi_int iw[SZ(@F@controller_SZ_IW)];
static casadi_real w[SZ(@F@controller_SZ_W)];

static casadi_int nnz(const casadi_int *sp) {
  casadi_int ncol = sp[1];
  if (ncol > 0 && sp[2] == 1) return sp[0] * ncol;
  return sp[2 + ncol];
}

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

static double now_ns(void) {
  struct timespec ts;
#ifdef CLOCK_THREAD_CPUTIME_ID
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
#else
  clock_gettime(CLOCK_MONOTONIC, &ts);
#endif
  return (double) ts.tv_sec * 1e9 + (double) ts.tv_nsec;
}

int main(int argc, char *argv[]) {
  const char *path = argc > 1 ? argv[1] : "trajectory.txt";
  long iterations = argc > 2 ? atol(argv[2]) : 200000;
  casadi_int n_in = @F@controller_n_in(), n_out = @F@controller_n_out(), i, total_in = 0, total_out = 0;
  long rows = 0, k;
  int mem, rep, got = 1;
  double best = -1.0, checksum = 0.0;
  FILE *fp;

  if (iterations < 1) iterations = 1;
  for (i = 0; i < n_in; ++i) total_in += nnz(@F@controller_sparsity_in(i));
  for (i = 0; i < n_out; ++i) {
    res[i] = out_values + total_out;
    total_out += nnz(@F@controller_sparsity_out(i));
  }
  if (total_in > MAX_IN || total_out > MAX_VALUES) {
    fprintf(stderr, "increase MAX_IN or MAX_VALUES\n");
    return 1;
  }
  fp = fopen(path, "r");
  if (!fp) {
    fprintf(stderr, "cannot open %s\n", path);
    return 1;
  }
  while (rows < MAX_ROWS) {
    got = read_number(fp, &in_values[rows][0]);
    if (got != 1) break;
    for (i = 1; got == 1 && i < total_in; ++i) got = read_number(fp, &in_values[rows][i]);
    if (got != 1) break;
    ++rows;
  }
  fclose(fp);
  if (rows == 0 || got == -1) {
    fprintf(stderr, "%s: no complete samples\n", path);
    return 1;
  }
  for (k = 0; k < rows; ++k) {
    casadi_int off = 0;
    for (i = 0; i < n_in; ++i) {
      arg[k][i] = in_values[k] + off;
      off += nnz(@F@controller_sparsity_in(i));
    }
  }
  @F@controller_incref();
  mem = @F@controller_checkout();
  for (rep = 0; rep < 5; ++rep) {
    double t0 = now_ns(), dt;
    for (k = 0; k < iterations; ++k) {
      @F@controller(arg[k % rows], res, iw, w, mem);
      checksum += res[0][0];
    }
    dt = (now_ns() - t0) / (double) iterations;
    if (best < 0.0 || dt < best) best = dt;
  }
  @F@controller_release(mem);
  @F@controller_decref();
  {
    /* t is input 0 (1 value), q input 1 and dq input 2 (N_JOINTS values each) */
    @P@state st;
    double tau[@UP@N_JOINTS], step_best = -1.0;
    for (rep = 0; rep < 5; ++rep) {
      double t0 = now_ns(), dt;
      for (k = 0; k < iterations; ++k) {
        const casadi_real *row = in_values[k % rows];
        if (k % rows == 0) @P@init(&st);
        if (@P@step(&st, row[0], row + 1, row + 1 + @UP@N_JOINTS, tau) < 0) {
          fprintf(stderr, "@P@step failed\n");
          return 1;
        }
        checksum += tau[0];
      }
      dt = (now_ns() - t0) / (double) iterations;
      if (step_best < 0.0 || dt < step_best) step_best = dt;
    }
    printf("ns_per_call %.3f iterations %ld checksum %.17g step_ns_per_call %.3f\n", best, iterations, checksum,
           step_best);
  }
  return 0;
}
