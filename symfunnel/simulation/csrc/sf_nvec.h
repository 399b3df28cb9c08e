/* The serial vector operations CVODES spends most of its own time in, four doubles at a time (AVX2, chosen at run
 * time), for symfunnel's CVODES driver (included by cvodes_driver.c).
 *
 * Why: a paper run's CVODES does ~40 vector operations per step on its 156 states (the Nordsieck array's
 * predictions and corrections, the Newton updates, the error weights): a fifth of the run in the SUNDIALS inside
 * CasADi's wheel, built for SSE2 (two doubles), with N_VAbs calling SUNRabs through the PLT per element and N_VMin
 * one compare chain. The operations here are SUNDIALS 2.6.1's N_VLinearSum, N_VScale, N_VAbs, N_VAddConst, N_VInv and
 * N_VMin for serial vectors, case for case (the same special cases of the coefficients, each element computed by
 * the same IEEE operations: a*x + y, c*(x + y), ...; no fused multiply-add), so every result is the same double;
 * only the width of the loops changes. The sums (N_VWrmsNorm, N_VDotProd) keep SUNDIALS' own code: their order of
 * addition is their result.
 *
 * They are installed in a vector's operation table (which CVODES' clones copy) only where that table holds,
 * slot for slot, the serial functions this SUNDIALS exports (linked by name) -- the layout this code was written
 * for -- and the processor has AVX2; otherwise the vector keeps SUNDIALS' functions. */
#ifndef SF_NVEC_H
#define SF_NVEC_H

#include <string.h>

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#define SF_NV_SIMD 1
#define SF_AVX2 __attribute__((target("avx2")))
#else
#define SF_NV_SIMD 0
#define SF_AVX2
#endif

#define SF_NV_SLOTS 25
/* SUNDIALS 2.6.1's serial vector functions (nvector_serial.h), the slots of its struct _generic_N_Vector_Ops in
 * order, and the serial vector's content */
N_Vector N_VClone_Serial(N_Vector w);
N_Vector N_VCloneEmpty_Serial(N_Vector w);
void N_VDestroy_Serial(N_Vector v);
void N_VSpace_Serial(N_Vector v, long int *lrw, long int *liw);
realtype *N_VGetArrayPointer_Serial(N_Vector v);
void N_VSetArrayPointer_Serial(realtype *v_data, N_Vector v);
void N_VLinearSum_Serial(realtype a, N_Vector x, realtype b, N_Vector y, N_Vector z);
void N_VConst_Serial(realtype c, N_Vector z);
void N_VProd_Serial(N_Vector x, N_Vector y, N_Vector z);
void N_VDiv_Serial(N_Vector x, N_Vector y, N_Vector z);
void N_VScale_Serial(realtype c, N_Vector x, N_Vector z);
void N_VAbs_Serial(N_Vector x, N_Vector z);
void N_VInv_Serial(N_Vector x, N_Vector z);
void N_VAddConst_Serial(N_Vector x, realtype b, N_Vector z);
realtype N_VDotProd_Serial(N_Vector x, N_Vector y);
realtype N_VMaxNorm_Serial(N_Vector x);
realtype N_VWrmsNorm_Serial(N_Vector x, N_Vector w);
realtype N_VWrmsNormMask_Serial(N_Vector x, N_Vector w, N_Vector id);
realtype N_VMin_Serial(N_Vector x);
realtype N_VWL2Norm_Serial(N_Vector x, N_Vector w);
realtype N_VL1Norm_Serial(N_Vector x);
void N_VCompare_Serial(realtype c, N_Vector x, N_Vector z);
booleantype N_VInvTest_Serial(N_Vector x, N_Vector z);
booleantype N_VConstrMask_Serial(N_Vector c, N_Vector x, N_Vector m);
realtype N_VMinQuotient_Serial(N_Vector num, N_Vector denom);
enum { SF_NV_LINEARSUM = 6, SF_NV_SCALE = 10, SF_NV_ABS = 11, SF_NV_INV = 12, SF_NV_ADDCONST = 13, SF_NV_MIN = 18 };

typedef void (*sf_nv_fn)(void);
typedef struct { sf_nv_fn slot[SF_NV_SLOTS]; } sf_nv_ops;
typedef struct { void *content; sf_nv_ops *ops; } sf_nv;
typedef struct { long int length; int own_data; double *data; } sf_nv_content;

#define SF_NV_LEN(v) (((sf_nv_content *) ((sf_nv *) (void *) (v))->content)->length)
#define SF_NV_DATA(v) (((sf_nv_content *) ((sf_nv *) (void *) (v))->content)->data)

/* z[i] = EXPR for i < n: four at a time (V: the __m256d form), then the rest (S: the scalar form) */
#define SF_NV_LOOP(V, S) do { for (i = 0; i + 4 <= n; i += 4) { V; } for (; i < n; ++i) { S; } } while (0)
#define LD(p) _mm256_loadu_pd((p) + i)
#define ST(p, v) _mm256_storeu_pd((p) + i, (v))

/* d = CVodeGetDky's interpolation at k = 0 from Nordsieck columns z[0..q] and s = (t - tn)/h: v = z[q], then
 * v = s v + z[j] for j = q-1..0 (N_VScale(1) and N_VLinearSum(1, z[j], s, dky, dky) element by element: the same
 * doubles), one pass over the elements; scalar form */
static void sf_horner_scalar(double s, const double *const *z, int q, double *d, long n) {
  long i;
  int l;
  for (i = 0; i < n; ++i) {
    double v = z[q][i];
    for (l = q - 1; l >= 0; --l) v = s * v + z[l][i];
    d[i] = v;
  }
}

#if SF_NV_SIMD
/* sf_horner_scalar four elements at a time */
SF_AVX2 static void sf_horner(double s, const double *const *z, int q, double *d, long n) {
  long i;
  int l;
  __m256d vs = _mm256_set1_pd(s);
#define SF_H(j) v = _mm256_add_pd(_mm256_mul_pd(vs, v), LD(z[j]))
  switch (q) {                /* BDF's orders 1..5 unrolled; the same operations in the same order as the loop */
  case 1: for (i = 0; i + 4 <= n; i += 4) { __m256d v = LD(z[1]); SF_H(0); ST(d, v); } break;
  case 2: for (i = 0; i + 4 <= n; i += 4) { __m256d v = LD(z[2]); SF_H(1); SF_H(0); ST(d, v); } break;
  case 3: for (i = 0; i + 4 <= n; i += 4) { __m256d v = LD(z[3]); SF_H(2); SF_H(1); SF_H(0); ST(d, v); } break;
  case 4:
    for (i = 0; i + 4 <= n; i += 4) { __m256d v = LD(z[4]); SF_H(3); SF_H(2); SF_H(1); SF_H(0); ST(d, v); }
    break;
  case 5:
    for (i = 0; i + 4 <= n; i += 4) { __m256d v = LD(z[5]); SF_H(4); SF_H(3); SF_H(2); SF_H(1); SF_H(0); ST(d, v); }
    break;
  default:
    for (i = 0; i + 4 <= n; i += 4) {
      __m256d v = LD(z[q]);
      for (l = q - 1; l >= 0; --l) SF_H(l);
      ST(d, v);
    }
  }
#undef SF_H
  /* the rest here, not by a (tail) call to sf_horner_scalar: gcc 12 compiles that call to a jump without the
   * vzeroupper, and the SSE code after it (the closed loop's functions) ran a paper run 1.8x slower on this Xeon */
  i = n - n % 4;
  for (; i < n; ++i) {
    double v = z[q][i];
    for (l = q - 1; l >= 0; --l) v = s * v + z[l][i];
    d[i] = v;
  }
}

SF_AVX2 static void sf_nv_axpy(double a, const double *x, double *y, long n) {   /* y <- a x + y */
  long i;
  __m256d va = _mm256_set1_pd(a);
  if (a == 1.0) SF_NV_LOOP(ST(y, _mm256_add_pd(LD(y), LD(x))), y[i] = y[i] + x[i]);
  else if (a == -1.0) SF_NV_LOOP(ST(y, _mm256_sub_pd(LD(y), LD(x))), y[i] = y[i] - x[i]);
  else SF_NV_LOOP(ST(y, _mm256_add_pd(LD(y), _mm256_mul_pd(va, LD(x)))), y[i] = y[i] + a * x[i]);
}

/* N_VLinearSum: z = a x + b y, by SUNDIALS' cases */
SF_AVX2 static void sf_nv_linearsum(realtype a, N_Vector X, realtype b, N_Vector Y, N_Vector Z) {
  long i, n = SF_NV_LEN(X);
  const double *x = SF_NV_DATA(X), *y = SF_NV_DATA(Y), *u, *v;
  double *z = SF_NV_DATA(Z), c;
  __m256d vc, va = _mm256_set1_pd(a), vb = _mm256_set1_pd(b);
  int test;
  if (b == 1.0 && Z == Y) { sf_nv_axpy(a, x, z, n); return; }
  if (a == 1.0 && Z == X) { sf_nv_axpy(b, y, z, n); return; }
  if (a == 1.0 && b == 1.0) { SF_NV_LOOP(ST(z, _mm256_add_pd(LD(x), LD(y))), z[i] = x[i] + y[i]); return; }
  if ((test = (a == 1.0 && b == -1.0)) || (a == -1.0 && b == 1.0)) {        /* z = v - u */
    u = test ? y : x;
    v = test ? x : y;
    SF_NV_LOOP(ST(z, _mm256_sub_pd(LD(v), LD(u))), z[i] = v[i] - u[i]);
    return;
  }
  if ((test = (a == 1.0)) || b == 1.0) {                                     /* z = c u + v */
    c = test ? b : a;
    u = test ? y : x;
    v = test ? x : y;
    vc = _mm256_set1_pd(c);
    SF_NV_LOOP(ST(z, _mm256_add_pd(_mm256_mul_pd(vc, LD(u)), LD(v))), z[i] = (c * u[i]) + v[i]);
    return;
  }
  if ((test = (a == -1.0)) || b == -1.0) {                                   /* z = c u - v */
    c = test ? b : a;
    u = test ? y : x;
    v = test ? x : y;
    vc = _mm256_set1_pd(c);
    SF_NV_LOOP(ST(z, _mm256_sub_pd(_mm256_mul_pd(vc, LD(u)), LD(v))), z[i] = (c * u[i]) - v[i]);
    return;
  }
  if (a == b) { SF_NV_LOOP(ST(z, _mm256_mul_pd(va, _mm256_add_pd(LD(x), LD(y)))), z[i] = a * (x[i] + y[i])); return; }
  if (a == -b) { SF_NV_LOOP(ST(z, _mm256_mul_pd(va, _mm256_sub_pd(LD(x), LD(y)))), z[i] = a * (x[i] - y[i])); return; }
  SF_NV_LOOP(ST(z, _mm256_add_pd(_mm256_mul_pd(va, LD(x)), _mm256_mul_pd(vb, LD(y)))),
             z[i] = (a * x[i]) + (b * y[i]));
}

/* N_VScale: z = c x (x scaled in place, copied, negated or multiplied, as SUNDIALS' cases) */
SF_AVX2 static void sf_nv_scale(realtype c, N_Vector X, N_Vector Z) {
  long i, n = SF_NV_LEN(X);
  const double *x = SF_NV_DATA(X);
  double *z = SF_NV_DATA(Z);
  __m256d vc = _mm256_set1_pd(c);
  if (Z == X) { SF_NV_LOOP(ST(z, _mm256_mul_pd(vc, LD(z))), z[i] = z[i] * c); return; }
  if (c == 1.0) { memcpy(z, x, (size_t) n * sizeof(double)); return; }
  if (c == -1.0) { SF_NV_LOOP(ST(z, _mm256_xor_pd(_mm256_set1_pd(-0.0), LD(x))), z[i] = -x[i]); return; }
  SF_NV_LOOP(ST(z, _mm256_mul_pd(vc, LD(x))), z[i] = c * x[i]);
}

/* N_VAbs: z = |x| (SUNRabs here is fabs: the sign bit cleared) */
SF_AVX2 static void sf_nv_abs(N_Vector X, N_Vector Z) {
  long i, n = SF_NV_LEN(X);
  const double *x = SF_NV_DATA(X);
  double *z = SF_NV_DATA(Z);
  __m256d sign = _mm256_set1_pd(-0.0);
  SF_NV_LOOP(ST(z, _mm256_andnot_pd(sign, LD(x))), z[i] = fabs(x[i]));
}

/* N_VAddConst: z = x + b */
SF_AVX2 static void sf_nv_addconst(N_Vector X, realtype b, N_Vector Z) {
  long i, n = SF_NV_LEN(X);
  const double *x = SF_NV_DATA(X);
  double *z = SF_NV_DATA(Z);
  __m256d vb = _mm256_set1_pd(b);
  SF_NV_LOOP(ST(z, _mm256_add_pd(LD(x), vb)), z[i] = x[i] + b);
}

/* N_VInv: z = 1 / x */
SF_AVX2 static void sf_nv_inv(N_Vector X, N_Vector Z) {
  long i, n = SF_NV_LEN(X);
  const double *x = SF_NV_DATA(X);
  double *z = SF_NV_DATA(Z);
  __m256d one = _mm256_set1_pd(1.0);
  SF_NV_LOOP(ST(z, _mm256_div_pd(one, LD(x))), z[i] = 1.0 / x[i]);
}

/* N_VMin: x[0], then each later x[i] < the running minimum replaces it (NaNs after x[0] skipped). Four running
 * minima give the same value, except which zero (+0 or -0) comes first: a zero result is found again in order. */
SF_AVX2 static realtype sf_nv_min(N_Vector X) {
  long i, n = SF_NV_LEN(X);
  const double *x = SF_NV_DATA(X);
  double m = x[0], lane[4];
  __m256d vm = _mm256_set1_pd(m);
  if (m != m) return m;
  for (i = 1; i + 4 <= n; i += 4) vm = _mm256_min_pd(LD(x), vm);      /* x[i] < vm ? x[i] : vm, lane by lane */
  _mm256_storeu_pd(lane, vm);
  for (; i < n; ++i) if (x[i] < m) m = x[i];
  for (i = 0; i < 4; ++i) if (lane[i] < m) m = lane[i];
  if (m == 0.0)
    for (m = x[0], i = 1; i < n; ++i) if (x[i] < m) m = x[i];
  return m;
}
#endif

#undef LD
#undef ST

/* Install the four-wide operations in vector v's operation table: 1 when installed; 0 when v keeps SUNDIALS'
 * (no AVX2 here, or a table that is not slot for slot the serial one this code knows). */
static int sf_nv_install(N_Vector v) {
#if SF_NV_SIMD
  const sf_nv_fn want[SF_NV_SLOTS] = {
    (sf_nv_fn) N_VClone_Serial, (sf_nv_fn) N_VCloneEmpty_Serial, (sf_nv_fn) N_VDestroy_Serial,
    (sf_nv_fn) N_VSpace_Serial, (sf_nv_fn) N_VGetArrayPointer_Serial, (sf_nv_fn) N_VSetArrayPointer_Serial,
    (sf_nv_fn) N_VLinearSum_Serial, (sf_nv_fn) N_VConst_Serial, (sf_nv_fn) N_VProd_Serial, (sf_nv_fn) N_VDiv_Serial,
    (sf_nv_fn) N_VScale_Serial, (sf_nv_fn) N_VAbs_Serial, (sf_nv_fn) N_VInv_Serial, (sf_nv_fn) N_VAddConst_Serial,
    (sf_nv_fn) N_VDotProd_Serial, (sf_nv_fn) N_VMaxNorm_Serial, (sf_nv_fn) N_VWrmsNorm_Serial,
    (sf_nv_fn) N_VWrmsNormMask_Serial, (sf_nv_fn) N_VMin_Serial, (sf_nv_fn) N_VWL2Norm_Serial,
    (sf_nv_fn) N_VL1Norm_Serial, (sf_nv_fn) N_VCompare_Serial, (sf_nv_fn) N_VInvTest_Serial,
    (sf_nv_fn) N_VConstrMask_Serial, (sf_nv_fn) N_VMinQuotient_Serial};
  sf_nv_ops *ops = ((sf_nv *) (void *) v)->ops;
  int k;
  __builtin_cpu_init();
  if (!__builtin_cpu_supports("avx2") || !ops) return 0;
  for (k = 0; k < SF_NV_SLOTS; ++k)
    if (ops->slot[k] != want[k]) return 0;
  ops->slot[SF_NV_LINEARSUM] = (sf_nv_fn) sf_nv_linearsum;
  ops->slot[SF_NV_SCALE] = (sf_nv_fn) sf_nv_scale;
  ops->slot[SF_NV_ABS] = (sf_nv_fn) sf_nv_abs;
  ops->slot[SF_NV_INV] = (sf_nv_fn) sf_nv_inv;
  ops->slot[SF_NV_ADDCONST] = (sf_nv_fn) sf_nv_addconst;
  ops->slot[SF_NV_MIN] = (sf_nv_fn) sf_nv_min;
  return 1;
#else
  (void) v;
  return 0;
#endif
}

#endif
