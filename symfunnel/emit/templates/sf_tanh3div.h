/* ---- @P@tanh, the previous form (three divisions per lane), kept as `symfunnel bench`'s baseline (tanh3div_ns) --
 * a branch-free tanh the compiler can vectorise over an array (no libm call, no table)
 *   |x| <  0.625: x + x z P(z)/Q(z), z = x^2       (Cephes tanh.c rational form)
 *   |x| >= 0.625: 1 - 2e/(1 + e), e = exp(-2|x|)   (exp: Cephes exp.c Pade form, 2^n built from its bits)
 * sign restored with copysign, |x| clamped to 20 (tanh = 1 to double precision beyond 19.06), NaN -> NaN.
 * Both branches are computed and one is selected on the bit patterns (integer compares do not trap, so the loop
 * if-converts under the default -ftrapping-math): with -O2 -march=x86-64-v2 and up (or -O3) the reservoir's
 * tanh loop runs 2-8 lanes wide. Error against glibc's tanh: at most 2 ulp, absolute at most 2.3e-16 on
 * [-25, 25]; +-0, +-inf, NaN and denormals exact (tests/test_kernel.py). Compile with -DSYMFUNNEL_LIBM_TANH for
 * libm's tanh instead (then the step equals the CasADi graph's evaluation bit for bit where the sums agree).
 * Without a vector unit that compares 64-bit integers (x86-64 before SSE4.2: -march=x86-64-v2 or newer has one;
 * AArch64 always) the loop cannot vectorise and libm's tanh is faster: it is then used unless
 * -DSYMFUNNEL_FAST_TANH. */
#if !defined(SYMFUNNEL_LIBM_TANH) && !defined(SYMFUNNEL_FAST_TANH) \
    && !(defined(__SSE4_2__) || defined(__AVX2__) || defined(__aarch64__) || defined(__ARM_NEON))
#define SYMFUNNEL_LIBM_TANH
#endif
#ifdef SYMFUNNEL_LIBM_TANH
#define @P@tanh tanh
#else
static double @P@exp_neg(double y) {            /* exp(y) for y in [-40, 0] */
  const double LOG2E = 1.4426950408889634073599, C1 = 6.93145751953125E-1, C2 = 1.42860682030941723212E-6;
  const double MAGIC = 6755399441055744.0;      /* 1.5 * 2^52: rounds to the nearest integer */
  double v = LOG2E * y + MAGIC, n = v - MAGIC, r, rr, px, e, scale;
  uint64_t bits;
  memcpy(&bits, &v, sizeof bits);               /* the low 12 bits of v's pattern are n mod 2^12 */
  r = y - n * C1;
  r = r - n * C2;
  rr = r * r;
  px = r * ((1.26177193074810590878E-4 * rr + 3.02994407707441961300E-2) * rr + 9.99999999999999999910E-1);
  e = px / ((((3.00198505138664455042E-6 * rr + 2.52448340349684104192E-3) * rr + 2.27265548208155028766E-1) * rr
             + 2.00000000000000000009E0) - px);
  e = 1.0 + 2.0 * e;
  bits = (bits + 1023u) << 52;                  /* 2^n: biased exponent n + 1023 in [965, 1023] */
  memcpy(&scale, &bits, sizeof scale);
  return e * scale;
}

static double @P@tanh(double x) {
  /* for a = |x| >= 0 the bit patterns order as the values do, NaN above +inf */
  const int64_t B20 = 0x4034000000000000, B0625 = 0x3FE4000000000000, BINF = 0x7FF0000000000000;
  double a = fabs(x), z, small, e, large, r, twenty = 20.0;
  int64_t ab, tb, sb, lb, m;
  memcpy(&ab, &a, sizeof ab);
  memcpy(&tb, &twenty, sizeof tb);
  m = -(int64_t) (ab < B20);                    /* a < 20 (false for NaN) */
  tb = (ab & m) | (tb & ~m);
  memcpy(&a, &tb, sizeof a);                    /* a = min(a, 20); NaN -> 20, restored below */
  z = a * a;
  small = a + a * z * (((-9.64399179425052238628E-1 * z - 9.92877231001918586564E1) * z
                        - 1.61468768441708447952E3)
                       / (((z + 1.12811678491632931402E2) * z + 2.23548839060100448583E3) * z
                          + 4.84406305325125486048E3));
  e = @P@exp_neg(-2.0 * a);
  large = 1.0 - 2.0 * e / (1.0 + e);
  memcpy(&sb, &small, sizeof sb);
  memcpy(&lb, &large, sizeof lb);
  m = -(int64_t) (ab < B0625);
  sb = (sb & m) | (lb & ~m);                    /* a < 0.625 ? small : large */
  memcpy(&r, &sb, sizeof r);
  r = copysign(r, x);
  memcpy(&sb, &r, sizeof sb);
  memcpy(&lb, &x, sizeof lb);
  m = -(int64_t) (ab > BINF);                   /* NaN in, NaN out */
  sb = (lb & m) | (sb & ~m);
  memcpy(&r, &sb, sizeof r);
  return r;
}
#endif
