/* Example control loop around the generated controller: one @P@step call per sample.
 *
 *   make && ./symfunnel_main trajectory.txt          (make run)
 *   ./symfunnel_main trajectory.txt loop
 *
 * Each line of the trajectory holds a recorded sample in the order of manifest.json
 * (t, q, dq, qd, dqd, ddqd, x_esn, w_hat; matrices column-major); lines starting with '#' are comments.
 * The program feeds t, q and dq of each sample to @P@step, as a robot's loop feeds its measurements, and prints
 * t and the torque tau, one line per sample. By default it first restores the controller state (x_esn, w_hat)
 * recorded with the sample, so that every printed torque can be checked against the design at that sample;
 * with "loop" it calls @P@init once and lets @P@step carry the state, as on the robot.
 * Static memory only: no casadi, no malloc.
 */
#include <stdio.h>
#include <string.h>
#include "@BASENAME@.h"

#define N @UP@N_JOINTS
#define NX @UP@ROW_ESN
#define NW (@UP@ROW_REGRESSOR * @UP@N_JOINTS)
#define ROW (1 + 5 * N + NX + NW)

static double row[ROW];

/* Read the next number, skipping white space and '#' comment lines; 1 on success, 0 at end of file, -1 on junk. */
static int read_number(FILE *fp, double *x) {
  int c;
  for (;;) {
    c = fgetc(fp);
    if (c == EOF) return 0;
    if (c == '#') {
      while (c != '\n' && c != EOF) c = fgetc(fp);
      continue;
    }
    if (c == ' ' || c == '\t' || c == '\n' || c == '\r') continue;
    ungetc(c, fp);
    return fscanf(fp, "%lf", x) == 1 ? 1 : -1;
  }
}

int main(int argc, char *argv[]) {
  const char *path = argc > 1 ? argv[1] : "trajectory.txt";
  int loop = argc > 2 && strcmp(argv[2], "loop") == 0;
  @P@state s;
  double tau[N];
  long samples = 0;
  int i, rc, status = 0;
  FILE *fp = fopen(path, "r");

  if (!fp) {
    fprintf(stderr, "cannot open %s\n", path);
    return 1;
  }
  @P@init(&s);
  printf("# t");
  for (i = 0; i < N; ++i) printf(" tau%d", i + 1);
  printf("\n");
  for (;;) {
    int got = read_number(fp, &row[0]);
    if (got == 0) break;
    for (i = 1; got == 1 && i < ROW; ++i) got = read_number(fp, &row[i]);
    if (got != 1) {
      fprintf(stderr, "%s: sample %ld: expected %d numbers\n", path, samples + 1, ROW);
      status = 1;
      break;
    }
    if (!loop) {                       /* restore the recorded controller state */
      memcpy(s.x_esn, row + 1 + 5 * N, NX * sizeof(double));
      memcpy(s.w_hat, row + 1 + 5 * N + NX, NW * sizeof(double));
    }
    rc = @P@step(&s, row[0], row + 1, row + 1 + N, tau);   /* t, q, dq: the measurements */
    if (rc < 0) {
      fprintf(stderr, "sample %ld: @P@step failed (%d)\n", samples + 1, rc);
      status = 1;
      break;
    }
    if (rc == 1) fprintf(stderr, "sample %ld: outside a funnel\n", samples + 1);
    printf("%.17g", row[0]);
    for (i = 0; i < N; ++i) printf(" %.17g", tau[i]);
    printf("\n");
    ++samples;
  }
  fclose(fp);
  if (!status && samples == 0) {
    fprintf(stderr, "%s: no samples\n", path);
    status = 1;
  }
  return status;
}
