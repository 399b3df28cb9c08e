/* ---- @P@tanh: a branch-free tanh the compiler can vectorise over an array (no libm call, no table) ---------
 * One division per lane: r = c + n / d with (c, n, d) selected per lane on a = min(|x|, 20):
 *   a <  0.625: c = a, n = a z P(z), d = Q(z), z = a^2     (Cephes tanh.c's rational form a + a z P/Q)
 *   a >= 0.625: c = 1, n = -2B, d = A + B                  (1 - 2e/(1 + e) with e = exp(-2a) = B/A)
 * where exp(-2a) = 2^k exp(t), k = round(-2a / ln 2), t = -2a - k ln 2 (Cody-Waite, |t| <= ln2/2), and Cephes
 * exp.c's Pade form exp(t) = (q(t^2) + t p(t^2)) / (q(t^2) - t p(t^2)) is kept as the pair A = q - tp,
 * B = 2^k (q + tp) (2^k built from its bits) instead of being divided out: the previous form divided three times
 * per lane (that rational, the Pade quotient, 2e/(1 + e)); this one divides once and with -mfma (-march=native on
 * x86-64 since Haswell, AArch64) its multiply-adds are fused (fma(), inlined; -DSYMFUNNEL_NO_FMA for the
 * unfused form). Sign restored with copysign, |x| clamped to 20 (tanh = 1 to double precision beyond 19.06),
 * NaN -> NaN.
 * All candidates are computed and selected on the bit patterns (integer compares do not trap, so the loop
 * if-converts under the default -ftrapping-math): with -O2 -march=x86-64-v2 and up (or -O3) the reservoir's
 * tanh loop runs 2-8 lanes wide.
 * Error bound: at most 1.8 ulp and 2.0e-16 absolute from the exact tanh (tests/test_tanh.py; measured, also within
 * the previous 2 ulp and 2.3e-16 of glibc's, tests/test_kernel.py); +-0, +-inf, NaN and denormals exact. Why, to first order in
 * u = 2^-53: the two rational approximations' own errors are below 0.05 u (mpmath, double coefficients, on
 * (0, 0.625] and |t| <= ln2/2). Small branch: |n/d| = a - tanh(a) <= 0.127 r, so the <= 4 u of z, P, Q, the two
 * products and the division count 0.51 u, plus the final addition's 0.5 u: relative <= 1.05 u, <= 1.05 ulp.
 * Large branch: t is exact to 0.2 u (k C1 exact, Sterbenz), A and B within 1.5 u each (q in [2, 2.03] and
 * |t p| <= 0.35 give A, q + tp >= 1.65; 2^k exact); w = 2B/(A + B) = 2e/(1 + e) within (|dA| + |dB|)/(1 + e)
 * + 1 u (the sum, the division), and r = 1 - w within w (3 u/(1 + e) + 1 u) + 0.5 u r: at the seam (e = 0.2865,
 * w = 0.4454, r = 0.5546, ulp = u) 1.76 u = 1.76 ulp, falling with a as w ~ 2e. Measured against a correctly
 * rounded reference (numpy longdouble tanh, itself within 0.001 ulp of mpmath) over 1.05e7 points covering both
 * branches, the seam 0.625, the clamp, the exp's reduction boundaries, subnormals and +-0, with and without fma:
 * max 1.58 ulp (x = 0.62583), 1.76e-16 absolute; the previous form 1.57 ulp, 1.74e-16.
 * Compile with -DSYMFUNNEL_LIBM_TANH for libm's tanh instead (then the step equals the CasADi graph's evaluation
 * bit for bit where the sums agree). Without a vector unit that compares 64-bit integers (x86-64 before SSE4.2:
 * -march=x86-64-v2 or newer has one; AArch64 always) the loop cannot vectorise and libm's tanh is faster: it is
 * then used unless -DSYMFUNNEL_FAST_TANH. */
#if !defined(SYMFUNNEL_LIBM_TANH) && !defined(SYMFUNNEL_FAST_TANH) \
    && !(defined(__SSE4_2__) || defined(__AVX2__) || defined(__aarch64__) || defined(__ARM_NEON))
#define SYMFUNNEL_LIBM_TANH
#endif
#ifdef SYMFUNNEL_LIBM_TANH
#define @P@tanh tanh
#else
#if (defined(__FMA__) || defined(__ARM_FEATURE_FMA)) && !defined(SYMFUNNEL_NO_FMA)
#define @P@ma(a, b, c) fma(a, b, c)                /* one rounding, inlined by the compiler */
#else
#define @P@ma(a, b, c) ((a) * (b) + (c))           /* fma() would be a library call here */
#endif
static double @P@tanh(double x) {
  /* for a = |x| >= 0 the bit patterns order as the values do, NaN above +inf */
  const int64_t B20 = 0x4034000000000000, B0625 = 0x3FE4000000000000, BINF = 0x7FF0000000000000;
  const double LOG2E = 1.4426950408889634073599, C1 = 6.93145751953125E-1, C2 = 1.42860682030941723212E-6;
  const double MAGIC = 6755399441055744.0;      /* 1.5 * 2^52: rounds to the nearest integer */
  double a = fabs(x), y, v, k, t, tt, px, qx, s, A, B, z, c, n, d, r, one = 1.0, twenty = 20.0;
  int64_t ab, tb, m, cs, cl, ns, nl, ds, dl;
  uint64_t bits;
  memcpy(&ab, &a, sizeof ab);
  memcpy(&tb, &twenty, sizeof tb);
  m = -(int64_t) (ab < B20);                    /* a < 20 (false for NaN) */
  tb = (ab & m) | (tb & ~m);
  memcpy(&a, &tb, sizeof a);                    /* a = min(a, 20); NaN -> 20, restored below */
  /* small |x|: c = a, n = a z P(z), d = Q(z) */
  z = a * a;
  n = a * z * @P@ma(@P@ma(-9.64399179425052238628E-1, z, -9.92877231001918586564E1), z, -1.61468768441708447952E3);
  d = @P@ma(@P@ma(z + 1.12811678491632931402E2, z, 2.23548839060100448583E3), z, 4.84406305325125486048E3);
  memcpy(&cs, &a, sizeof cs);
  memcpy(&ns, &n, sizeof ns);
  memcpy(&ds, &d, sizeof ds);
  /* large |x|: e = exp(-2a) = 2^k (qx + px)/(qx - px) = B/A (Cephes exp.c's Pade form, its quotient not taken),
     1 - 2e/(1 + e) = 1 - 2B/(A + B): c = 1, n = -2B, d = A + B */
  y = -2.0 * a;
  v = @P@ma(-2.0 * LOG2E, a, MAGIC);              /* = LOG2E y + MAGIC, y off the critical path */
  k = v - MAGIC;
  memcpy(&bits, &v, sizeof bits);               /* the low 12 bits of v's pattern are k mod 2^12 */
  t = @P@ma(-k, C1, y);                         /* exact: k C1 has <= 21 significant bits, Sterbenz */
  t = @P@ma(-k, C2, t);
  tt = t * t;
  px = t * @P@ma(@P@ma(1.26177193074810590878E-4, tt, 3.02994407707441961300E-2), tt, 9.99999999999999999910E-1);
  qx = @P@ma(@P@ma(@P@ma(3.00198505138664455042E-6, tt, 2.52448340349684104192E-3), tt, 2.27265548208155028766E-1),
             tt, 2.00000000000000000009E0);
  bits = (bits + 1023u) << 52;                  /* 2^k: biased exponent k + 1023 in [965, 1023] */
  memcpy(&s, &bits, sizeof s);
  A = qx - px;
  B = s * (qx + px);
  n = -2.0 * B;
  d = A + B;
  memcpy(&cl, &one, sizeof cl);
  memcpy(&nl, &n, sizeof nl);
  memcpy(&dl, &d, sizeof dl);
  m = -(int64_t) (ab < B0625);                  /* a < 0.625 ? small : large, for c, n and d */
  cs = (cs & m) | (cl & ~m);
  ns = (ns & m) | (nl & ~m);
  ds = (ds & m) | (dl & ~m);
  memcpy(&c, &cs, sizeof c);
  memcpy(&n, &ns, sizeof n);
  memcpy(&d, &ds, sizeof d);
  r = c + n / d;                                /* the one division */
  r = copysign(r, x);
  memcpy(&cs, &r, sizeof cs);
  memcpy(&nl, &x, sizeof nl);
  m = -(int64_t) (ab > BINF);                   /* NaN in, NaN out */
  cs = (nl & m) | (cs & ~m);
  memcpy(&r, &cs, sizeof r);
  return r;
}
#endif
