//! The sixteen-lane vector the CPU kernels are written against.
//!
//! A tile of the sparse layout is [`LANES`] = 16 vertices, one lane each. The blend kernel is
//! generic over [`Lanes`] and instantiated per instruction set, each inside a function compiled
//! with that set enabled and chosen once at run time:
//! - [`Avx512`]: one 512-bit register per 16 lanes;
//! - [`Avx2`]: a pair of 256-bit registers;
//! - [`Portable`]: plain arrays, whatever the baseline target vectorises.
//!
//! All compute the same sums; the FMA paths round once per multiply-add instead of twice, which
//! is far inside the engines' stated tolerance.

/// Lanes per vector and vertices per tile of the sparse layout.
pub const LANES: usize = 16;

/// Per-component constants of q16 output for one tile's 48 interleaved floats (x0 y0 z0 x1
/// ...): component `k` belongs to axis `k % 3`. See [`crate::Q16Params`].
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Q16Pattern {
    /// Subtracted before scaling, per component.
    pub sub: [f32; 3 * LANES],
    /// Scale, per component.
    pub mul: [f32; 3 * LANES],
    /// Lower clamp of the scaled value.
    pub lo: f32,
    /// Upper clamp of the scaled value.
    pub hi: f32,
    /// Added to the rounded integer.
    pub add: i32,
}

impl Q16Pattern {
    /// The pattern of `p`.
    pub fn new(p: &crate::Q16Params) -> Q16Pattern {
        Q16Pattern {
            sub: std::array::from_fn(|k| p.sub[k % 3]),
            mul: std::array::from_fn(|k| p.mul[k % 3]),
            lo: p.lo,
            hi: p.hi,
            add: p.add,
        }
    }
}

/// Operations the kernels need on sixteen f32 lanes.
///
/// The output stage works on registers: a tile's accumulators (x, y, z of sixteen vertices)
/// are normalized (normal blending), interleaved into 48 floats, and converted to the wire
/// format (f32, binary16 or q16) before they are stored, so no pass ever re-reads an output.
/// Every implementation computes the conversions with the same IEEE operations as the scalar
/// reference ([`crate::Q16Params::quantize`], `half::f16::from_f32`), so all families
/// encode a given f32 value to the same bits.
///
/// # Safety
/// Implementations may require CPU features; callers must only use an implementation whose
/// features are present (checked once when the engine is created).
pub unsafe trait Lanes: Copy {
    /// Loads sixteen lanes from `p` (64-byte aligned).
    ///
    /// # Safety
    /// `p` must be valid for reading sixteen f32 and 64-byte aligned.
    unsafe fn load(p: *const f32) -> Self;
    /// Loads lane `i` from `base[idx[i]]`: undoes a chunk's vertex permutation in L1.
    ///
    /// # Safety
    /// `idx` must be readable for sixteen u16 and `base` readable at every index it holds.
    unsafe fn gather(base: *const f32, idx: *const u16) -> Self;
    /// All lanes `x`.
    ///
    /// # Safety
    /// Requires the implementation's CPU features.
    unsafe fn splat(x: f32) -> Self;
    /// `a * b + c`.
    ///
    /// # Safety
    /// Requires the implementation's CPU features.
    unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self;
    /// Scales each lane's (x, y, z) to unit length, as `v × (1 / sqrt(x·x + y·y + z·z))`
    /// (zero stays zero).
    ///
    /// # Safety
    /// Requires the implementation's CPU features.
    unsafe fn normalize(x: Self, y: Self, z: Self) -> (Self, Self, Self);
    /// Interleaves sixteen vertices given as x, y, z lanes into 48 floats (x0 y0 z0 x1 ...),
    /// returned as three sixteen-float values.
    ///
    /// # Safety
    /// Requires the implementation's CPU features.
    unsafe fn interleave(x: Self, y: Self, z: Self) -> [Self; 3];
    /// Stores the sixteen floats at `out`.
    ///
    /// # Safety
    /// `out` must be valid for writing sixteen f32.
    unsafe fn store(v: Self, out: *mut f32);
    /// Stores the sixteen floats as binary16 (round to nearest even) at `out`.
    ///
    /// # Safety
    /// `out` must be valid for writing sixteen u16.
    unsafe fn store_f16(v: Self, out: *mut u16);
    /// Stores the sixteen floats as q16 at `out`: `round_even(clamp((v - sub) × mul, lo, hi))
    /// + add` with `sub` and `mul` per lane (floats `k..k + 16` of `p`'s pattern).
    ///
    /// # Safety
    /// `out` must be valid for writing sixteen i16; `k + 16 <= 48`.
    unsafe fn store_q16(v: Self, p: &Q16Pattern, k: usize, out: *mut i16);
    /// Copies `n` bytes from `src` to `dst` bypassing the caches where the ISA can (streaming
    /// stores skip the read-for-ownership of lines that are about to be overwritten whole).
    /// Callers must run [`Lanes::fence`] before other threads may read `dst`.
    ///
    /// # Safety
    /// `src` must be readable and `dst` writable for `n` bytes; they must not overlap.
    unsafe fn copy_out(dst: *mut u8, src: *const u8, n: usize) {
        // SAFETY: forwarded from the caller.
        unsafe { std::ptr::copy_nonoverlapping(src, dst, n) }
    }
    /// Orders earlier streaming stores before later stores.
    ///
    /// # Safety
    /// Requires the implementation's CPU features.
    unsafe fn fence() {}
}

/// Baseline implementation on plain arrays.
#[derive(Clone, Copy)]
pub struct Portable([f32; LANES]);

// SAFETY: uses no CPU features beyond the baseline target.
unsafe impl Lanes for Portable {
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        // SAFETY: the caller guarantees sixteen readable floats.
        Portable(unsafe { *(p as *const [f32; LANES]) })
    }
    #[inline(always)]
    unsafe fn gather(base: *const f32, idx: *const u16) -> Self {
        // SAFETY: the caller guarantees sixteen indices, each readable in `base`.
        Portable(std::array::from_fn(|i| unsafe {
            *base.add(usize::from(*idx.add(i)))
        }))
    }
    #[inline(always)]
    unsafe fn splat(x: f32) -> Self {
        Portable([x; LANES])
    }
    #[inline(always)]
    unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self {
        // Fused, as the AVX kernels' and the GPU's `fma()`: every kernel family then rounds
        // alike, and a skinned rig's neutral (the reference of q16r residuals) is the GPU's
        // bit for bit. Native on aarch64. On x86 this family runs only without AVX2 (no FMA
        // instruction since 2013's CPUs lacks it) or when forced: there each lane is a call to
        // libm's fmaf, about 10× slower (`CROWDMORPH_SIMD=portable bench cpu` on an AVX-512
        // VM), which correctness is worth on a fallback.
        let mut r = c.0;
        for ((r, a), b) in r.iter_mut().zip(a.0).zip(b.0) {
            *r = a.mul_add(b, *r);
        }
        Portable(r)
    }
    #[inline(always)]
    unsafe fn normalize(x: Self, y: Self, z: Self) -> (Self, Self, Self) {
        let (mut x, mut y, mut z) = (x.0, y.0, z.0);
        for i in 0..LANES {
            let len2 = x[i] * x[i] + y[i] * y[i] + z[i] * z[i];
            let inv = if len2 > 0.0 { 1.0 / len2.sqrt() } else { 0.0 };
            x[i] *= inv;
            y[i] *= inv;
            z[i] *= inv;
        }
        (Portable(x), Portable(y), Portable(z))
    }
    #[inline(always)]
    unsafe fn interleave(x: Self, y: Self, z: Self) -> [Self; 3] {
        let mut o = [[0.0; LANES]; 3];
        for i in 0..LANES {
            for (c, v) in [x.0[i], y.0[i], z.0[i]].into_iter().enumerate() {
                let k = 3 * i + c;
                o[k / LANES][k % LANES] = v;
            }
        }
        o.map(Portable)
    }
    #[inline(always)]
    unsafe fn store(v: Self, out: *mut f32) {
        // SAFETY: the caller guarantees sixteen writable floats.
        unsafe { std::ptr::copy_nonoverlapping(v.0.as_ptr(), out, LANES) }
    }
    #[inline(always)]
    unsafe fn store_f16(v: Self, out: *mut u16) {
        for (i, x) in v.0.into_iter().enumerate() {
            // SAFETY: the caller guarantees sixteen writable u16.
            unsafe { *out.add(i) = half::f16::from_f32(x).to_bits() };
        }
    }
    #[inline(always)]
    unsafe fn store_q16(v: Self, p: &Q16Pattern, k: usize, out: *mut i16) {
        for (i, x) in v.0.into_iter().enumerate() {
            // The same operations as `Q16Params::quantize`.
            let u = (x - p.sub[k + i]) * p.mul[k + i];
            let u = if u > p.lo { u } else { p.lo };
            let u = if u < p.hi { u } else { p.hi };
            // SAFETY: the caller guarantees sixteen writable i16.
            unsafe { *out.add(i) = (u.round_ties_even() as i32 + p.add) as i16 };
        }
    }
}

#[cfg(target_arch = "x86_64")]
pub use x86::{Avx2, Avx512};

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Lanes, Q16Pattern};
    use std::arch::x86_64::*;

    /// AVX2 + FMA (+ F16C for binary16 output): sixteen lanes as two 256-bit halves.
    #[derive(Clone, Copy)]
    pub struct Avx2(__m256, __m256);

    /// Interleaves eight vertices' x, y, z into 24 floats.
    ///
    /// # Safety
    /// Requires AVX2.
    #[inline(always)]
    unsafe fn interleave8(x: __m256, y: __m256, z: __m256) -> [__m256; 3] {
        // SAFETY: forwarded from the caller.
        unsafe {
            // o0 = x0 y0 z0 x1 y1 z1 x2 y2; o1 = z2 x3 y3 z3 x4 y4 z4 x5; o2 = y5 z5 x6 y6 z6 x7 y7 z7
            let i = |a, b, c, d, e, f, g, h| _mm256_setr_epi32(a, b, c, d, e, f, g, h);
            let o0 = _mm256_blend_ps::<0b0010_0100>(
                _mm256_blend_ps::<0b1001_0010>(
                    _mm256_permutevar8x32_ps(x, i(0, 0, 0, 1, 0, 0, 2, 0)),
                    _mm256_permutevar8x32_ps(y, i(0, 0, 0, 0, 1, 0, 0, 2)),
                ),
                _mm256_permutevar8x32_ps(z, i(0, 0, 0, 0, 0, 1, 0, 0)),
            );
            let o1 = _mm256_blend_ps::<0b0100_1001>(
                _mm256_blend_ps::<0b0010_0100>(
                    _mm256_permutevar8x32_ps(x, i(0, 3, 0, 0, 4, 0, 0, 5)),
                    _mm256_permutevar8x32_ps(y, i(0, 0, 3, 0, 0, 4, 0, 0)),
                ),
                _mm256_permutevar8x32_ps(z, i(2, 0, 0, 3, 0, 0, 4, 0)),
            );
            let o2 = _mm256_blend_ps::<0b1001_0010>(
                _mm256_blend_ps::<0b0100_1001>(
                    _mm256_permutevar8x32_ps(x, i(0, 0, 6, 0, 0, 7, 0, 0)),
                    _mm256_permutevar8x32_ps(y, i(5, 0, 0, 6, 0, 0, 7, 0)),
                ),
                _mm256_permutevar8x32_ps(z, i(0, 5, 0, 0, 6, 0, 0, 7)),
            );
            [o0, o1, o2]
        }
    }

    /// Eight floats to q16 (see [`Lanes::store_q16`]) as eight i32.
    ///
    /// # Safety
    /// Requires AVX2; `sub` and `mul` readable for eight floats.
    #[inline(always)]
    unsafe fn q16_8(v: __m256, p: &Q16Pattern, k: usize) -> __m256i {
        // SAFETY: forwarded from the caller.
        unsafe {
            let u = _mm256_mul_ps(
                _mm256_sub_ps(v, _mm256_loadu_ps(p.sub.as_ptr().add(k))),
                _mm256_loadu_ps(p.mul.as_ptr().add(k)),
            );
            let u = _mm256_min_ps(_mm256_max_ps(u, _mm256_set1_ps(p.lo)), _mm256_set1_ps(p.hi));
            // The default rounding mode (MXCSR) is to nearest even.
            _mm256_add_epi32(_mm256_cvtps_epi32(u), _mm256_set1_epi32(p.add))
        }
    }

    // SAFETY: every method requires AVX2 and FMA, which the engine checks before choosing this
    // implementation; all callers are `#[target_feature(enable = "avx2,fma,f16c")]` functions.
    unsafe impl Lanes for Avx2 {
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            // SAFETY: the caller guarantees alignment and sixteen readable floats.
            unsafe { Avx2(_mm256_load_ps(p), _mm256_load_ps(p.add(8))) }
        }
        #[inline(always)]
        unsafe fn gather(base: *const f32, idx: *const u16) -> Self {
            // SAFETY: AVX2 is available; the caller guarantees the indices and their targets.
            unsafe {
                let lo = _mm256_cvtepu16_epi32(_mm_loadu_si128(idx.cast()));
                let hi = _mm256_cvtepu16_epi32(_mm_loadu_si128(idx.add(8).cast()));
                Avx2(
                    _mm256_i32gather_ps::<4>(base, lo),
                    _mm256_i32gather_ps::<4>(base, hi),
                )
            }
        }
        #[inline(always)]
        unsafe fn splat(x: f32) -> Self {
            // SAFETY: AVX is available (see the impl's safety note).
            unsafe { Avx2(_mm256_set1_ps(x), _mm256_set1_ps(x)) }
        }
        #[inline(always)]
        unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self {
            // SAFETY: FMA is available (see the impl's safety note).
            unsafe {
                Avx2(
                    _mm256_fmadd_ps(a.0, b.0, c.0),
                    _mm256_fmadd_ps(a.1, b.1, c.1),
                )
            }
        }
        #[inline(always)]
        unsafe fn normalize(x: Self, y: Self, z: Self) -> (Self, Self, Self) {
            // SAFETY: AVX is available (see the impl's safety note).
            unsafe {
                let half = |x: __m256, y: __m256, z: __m256| {
                    // Products and sums rounded one by one, as the portable code does.
                    let len2 = _mm256_add_ps(
                        _mm256_add_ps(_mm256_mul_ps(x, x), _mm256_mul_ps(y, y)),
                        _mm256_mul_ps(z, z),
                    );
                    let inv = _mm256_div_ps(_mm256_set1_ps(1.0), _mm256_sqrt_ps(len2));
                    let pos = _mm256_cmp_ps::<_CMP_GT_OQ>(len2, _mm256_setzero_ps());
                    let inv = _mm256_and_ps(inv, pos);
                    (
                        _mm256_mul_ps(x, inv),
                        _mm256_mul_ps(y, inv),
                        _mm256_mul_ps(z, inv),
                    )
                };
                let (a, b, c) = half(x.0, y.0, z.0);
                let (d, e, f) = half(x.1, y.1, z.1);
                (Avx2(a, d), Avx2(b, e), Avx2(c, f))
            }
        }
        #[inline(always)]
        unsafe fn interleave(x: Self, y: Self, z: Self) -> [Self; 3] {
            // SAFETY: AVX2 is available (see the impl's safety note).
            unsafe {
                let [a, b, c] = interleave8(x.0, y.0, z.0);
                let [d, e, f] = interleave8(x.1, y.1, z.1);
                [Avx2(a, b), Avx2(c, d), Avx2(e, f)]
            }
        }
        #[inline(always)]
        unsafe fn store(v: Self, out: *mut f32) {
            // SAFETY: AVX is available; the caller guarantees sixteen writable floats.
            unsafe {
                _mm256_storeu_ps(out, v.0);
                _mm256_storeu_ps(out.add(8), v.1);
            }
        }
        #[inline(always)]
        unsafe fn store_f16(v: Self, out: *mut u16) {
            // SAFETY: F16C is available (checked with AVX2); sixteen writable u16.
            unsafe {
                let a = _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(v.0);
                let b = _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(v.1);
                _mm_storeu_si128(out.cast(), a);
                _mm_storeu_si128(out.add(8).cast(), b);
            }
        }
        #[inline(always)]
        unsafe fn store_q16(v: Self, p: &Q16Pattern, k: usize, out: *mut i16) {
            // SAFETY: AVX2 is available; the caller guarantees the ranges.
            unsafe {
                let a = q16_8(v.0, p, k);
                let b = q16_8(v.1, p, k + 8);
                // In range after the clamp, so the saturation never acts; packing works per
                // 128-bit lane (a0..3 b0..3 a4..7 b4..7), which the permute puts in order.
                let packed = _mm256_packs_epi32(a, b);
                let ordered = _mm256_permute4x64_epi64::<0b11_01_10_00>(packed);
                _mm256_storeu_si256(out.cast(), ordered);
            }
        }
        #[inline(always)]
        unsafe fn copy_out(dst: *mut u8, src: *const u8, n: usize) {
            // SAFETY: AVX is available; the caller guarantees the ranges.
            unsafe {
                stream_copy::<32>(dst, src, n, |d, s| {
                    _mm256_stream_si256(d.cast(), _mm256_loadu_si256(s.cast()))
                })
            }
        }
        #[inline(always)]
        unsafe fn fence() {
            // SAFETY: SSE is part of x86-64.
            unsafe { _mm_sfence() }
        }
    }

    /// AVX-512F: sixteen lanes in one register.
    #[derive(Clone, Copy)]
    pub struct Avx512(__m512);

    // SAFETY: every method requires AVX-512F, which the engine checks before choosing this
    // implementation; all callers are `#[target_feature(enable = "avx512f")]` functions.
    unsafe impl Lanes for Avx512 {
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            // SAFETY: the caller guarantees alignment and sixteen readable floats.
            unsafe { Avx512(_mm512_load_ps(p)) }
        }
        #[inline(always)]
        unsafe fn gather(base: *const f32, idx: *const u16) -> Self {
            // SAFETY: AVX-512F is available; the caller guarantees the indices and their
            // targets.
            unsafe {
                let i = _mm512_cvtepu16_epi32(_mm256_loadu_si256(idx.cast()));
                Avx512(_mm512_i32gather_ps::<4>(i, base))
            }
        }
        #[inline(always)]
        unsafe fn splat(x: f32) -> Self {
            // SAFETY: AVX-512F is available (see the impl's safety note).
            unsafe { Avx512(_mm512_set1_ps(x)) }
        }
        #[inline(always)]
        unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self {
            // SAFETY: AVX-512F is available (see the impl's safety note).
            unsafe { Avx512(_mm512_fmadd_ps(a.0, b.0, c.0)) }
        }
        #[inline(always)]
        unsafe fn normalize(x: Self, y: Self, z: Self) -> (Self, Self, Self) {
            // SAFETY: AVX-512F is available (see the impl's safety note).
            unsafe {
                let (x, y, z) = (x.0, y.0, z.0);
                let len2 = _mm512_add_ps(
                    _mm512_add_ps(_mm512_mul_ps(x, x), _mm512_mul_ps(y, y)),
                    _mm512_mul_ps(z, z),
                );
                let pos = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(len2, _mm512_setzero_ps());
                let inv = _mm512_maskz_div_ps(pos, _mm512_set1_ps(1.0), _mm512_sqrt_ps(len2));
                (
                    Avx512(_mm512_mul_ps(x, inv)),
                    Avx512(_mm512_mul_ps(y, inv)),
                    Avx512(_mm512_mul_ps(z, inv)),
                )
            }
        }
        #[inline(always)]
        unsafe fn interleave(x: Self, y: Self, z: Self) -> [Self; 3] {
            // Output float k of the 48 is component k % 3 of vertex k / 3. Two-source permutes
            // pick x and y first (indices 0..15 = x, 16..31 = y), then z joins (16..31 = z).
            const fn tables() -> ([[i32; 16]; 3], [[i32; 16]; 3]) {
                let mut xy = [[0; 16]; 3];
                let mut with_z = [[0; 16]; 3];
                let mut o = 0;
                while o < 3 {
                    let mut i = 0;
                    while i < 16 {
                        let k = o * 16 + i;
                        let (v, c) = ((k / 3) as i32, k % 3);
                        xy[o][i] = if c == 1 { 16 + v } else { v };
                        with_z[o][i] = if c == 2 { 16 + v } else { i as i32 };
                        i += 1;
                    }
                    o += 1;
                }
                (xy, with_z)
            }
            static T: ([[i32; 16]; 3], [[i32; 16]; 3]) = tables();
            // SAFETY: AVX-512F is available (see the impl's safety note).
            unsafe {
                std::array::from_fn(|o| {
                    let ixy = _mm512_loadu_si512(T.0[o].as_ptr().cast());
                    let iz = _mm512_loadu_si512(T.1[o].as_ptr().cast());
                    let t = _mm512_permutex2var_ps(x.0, ixy, y.0);
                    Avx512(_mm512_permutex2var_ps(t, iz, z.0))
                })
            }
        }
        #[inline(always)]
        unsafe fn store(v: Self, out: *mut f32) {
            // SAFETY: AVX-512F is available; the caller guarantees sixteen writable floats.
            unsafe { _mm512_storeu_ps(out, v.0) }
        }
        #[inline(always)]
        unsafe fn store_f16(v: Self, out: *mut u16) {
            // SAFETY: AVX-512F is available; the caller guarantees sixteen writable u16.
            unsafe {
                let h = _mm512_cvtps_ph::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(v.0);
                _mm256_storeu_si256(out.cast(), h);
            }
        }
        #[inline(always)]
        unsafe fn store_q16(v: Self, p: &Q16Pattern, k: usize, out: *mut i16) {
            // SAFETY: AVX-512F is available; the caller guarantees the ranges.
            unsafe {
                let u = _mm512_mul_ps(
                    _mm512_sub_ps(v.0, _mm512_loadu_ps(p.sub.as_ptr().add(k))),
                    _mm512_loadu_ps(p.mul.as_ptr().add(k)),
                );
                let u = _mm512_min_ps(_mm512_max_ps(u, _mm512_set1_ps(p.lo)), _mm512_set1_ps(p.hi));
                let q = _mm512_add_epi32(
                    _mm512_cvt_roundps_epi32::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
                        u,
                    ),
                    _mm512_set1_epi32(p.add),
                );
                // In range after the clamp: truncating to 16 bits keeps the value.
                _mm256_storeu_si256(out.cast(), _mm512_cvtepi32_epi16(q));
            }
        }
        #[inline(always)]
        unsafe fn copy_out(dst: *mut u8, src: *const u8, n: usize) {
            // SAFETY: AVX-512F is available; the caller guarantees the ranges.
            unsafe {
                stream_copy::<64>(dst, src, n, |d, s| {
                    _mm512_stream_si512(d.cast(), _mm512_loadu_si512(s.cast()))
                })
            }
        }
        #[inline(always)]
        unsafe fn fence() {
            // SAFETY: SSE is part of x86-64.
            unsafe { _mm_sfence() }
        }
    }

    /// Copies with plain stores up to the first `W`-byte aligned address of `dst`, streams
    /// whole aligned vectors, and finishes the tail with plain stores.
    ///
    /// # Safety
    /// `src` readable and `dst` writable for `n` bytes, not overlapping; `stream(d, s)` must
    /// be a streaming store of `W` bytes from `s` to `W`-byte aligned `d`.
    #[inline(always)]
    unsafe fn stream_copy<const W: usize>(
        dst: *mut u8,
        src: *const u8,
        n: usize,
        stream: impl Fn(*mut u8, *const u8),
    ) {
        // SAFETY: every access stays inside the caller's ranges.
        unsafe {
            let head = (dst.align_offset(W)).min(n);
            std::ptr::copy_nonoverlapping(src, dst, head);
            let mut i = head;
            while i + W <= n {
                stream(dst.add(i), src.add(i));
                i += W;
            }
            std::ptr::copy_nonoverlapping(src.add(i), dst.add(i), n - i);
        }
    }

    /// Whether this CPU can run the AVX2 kernels.
    pub fn has_avx2() -> bool {
        std::is_x86_feature_detected!("avx2")
            && std::is_x86_feature_detected!("fma")
            && std::is_x86_feature_detected!("f16c")
    }

    /// Whether this CPU can run the AVX-512 kernels.
    pub fn has_avx512() -> bool {
        std::is_x86_feature_detected!("avx512f")
    }
}

/// Which kernel family the engine runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// AVX-512F (x86-64).
    Avx512,
    /// AVX2 with FMA and F16C (x86-64).
    Avx2Fma,
    /// Plain arrays; whatever the baseline target vectorises.
    Portable,
}

impl Isa {
    /// The best kernel family for this CPU. `CROWDMORPH_SIMD=avx2|portable` caps it (tests use
    /// this to check every family against the oracle).
    pub fn detect() -> Isa {
        let cap = std::env::var("CROWDMORPH_SIMD").unwrap_or_default();
        Self::available()
            .into_iter()
            .find(|isa| match cap.as_str() {
                "portable" => *isa == Isa::Portable,
                "avx2" => *isa != Isa::Avx512,
                _ => true,
            })
            .unwrap_or(Isa::Portable)
    }

    /// Every kernel family this CPU can run, best first.
    pub fn available() -> Vec<Isa> {
        let mut v = Vec::new();
        #[cfg(target_arch = "x86_64")]
        {
            if x86::has_avx512() {
                v.push(Isa::Avx512);
            }
            if x86::has_avx2() {
                v.push(Isa::Avx2Fma);
            }
        }
        v.push(Isa::Portable);
        v
    }

    /// Name for logs, bench output and `/readyz`'s `cpu_isa` (the values proto/README.md lists,
    /// and that `CROWDMORPH_SIMD` takes).
    pub fn name(self) -> &'static str {
        match self {
            Isa::Avx512 => "avx512",
            Isa::Avx2Fma => "avx2",
            Isa::Portable => "portable",
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::{Q16Params, Quantization};

    #[repr(align(64))]
    struct A([f32; 48]);

    /// Sixteen vertices through `normalize` (optionally), `interleave` and the three stores.
    fn stage<L: Lanes>(
        src: &[f32; 48],
        normalize: bool,
        q: &Q16Pattern,
    ) -> (Vec<u32>, Vec<u16>, Vec<i16>) {
        let src = A(*src);
        let (mut f, mut h, mut i) = ([0f32; 48], [0u16; 48], [0i16; 48]);
        // SAFETY: callers check the features; src is aligned and holds 48 floats; the outputs
        // hold 48 elements each.
        unsafe {
            let p = src.0.as_ptr();
            let (mut x, mut y, mut z) = (L::load(p), L::load(p.add(16)), L::load(p.add(32)));
            if normalize {
                (x, y, z) = L::normalize(x, y, z);
            }
            for (k, r) in L::interleave(x, y, z).into_iter().enumerate() {
                L::store(r, f.as_mut_ptr().add(16 * k));
                L::store_f16(r, h.as_mut_ptr().add(16 * k));
                L::store_q16(r, q, 16 * k, i.as_mut_ptr().add(16 * k));
            }
        }
        (
            f.iter().map(|v| v.to_bits()).collect(),
            h.to_vec(),
            i.to_vec(),
        )
    }

    #[test]
    fn output_stage_of_every_family_matches_the_scalar_reference() {
        // Values around rounding boundaries of binary16 and of the q16 grid, subnormals,
        // overflow, signs, zeros (normalize keeps them zero), and values outside the box.
        let b = Quantization {
            min: [-1.5, -0.25, 2.0],
            step: [3.0 / 65535.0, 0.5 / 65535.0, 1e-3],
            max_error: [0.0; 3],
        };
        let mut seed = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let specials = [
            65520.0,
            1e-7,
            -1e-5,
            0.0,
            -0.0,
            1.0 + 1.0 / 2048.0,
            1e30,
            -1e30,
        ];
        for round in 0..200 {
            let src: [f32; 48] = std::array::from_fn(|k| match round % 4 {
                0 => specials[k % specials.len()],
                1 => (next() - 0.5) * 8.0,
                // Exactly on and next to the q16 grid of the box.
                2 => {
                    let a = k % 3;
                    let n = (next() * 65535.0).floor() + [0.0, 0.5, 0.25][k % 3];
                    b.min[a] + n * b.step[a]
                }
                _ => {
                    if k % 5 == 0 {
                        0.0
                    } else {
                        next() * 2.0 - 1.0
                    }
                }
            });
            for normals in [false, true] {
                let q = Q16Pattern::new(&Q16Params::new(b, normals));
                let want = stage::<Portable>(&src, normals, &q);
                // The portable stage is the scalar reference.
                let params = Q16Params::new(b, normals);
                let f: Vec<f32> = want.0.iter().map(|&u| f32::from_bits(u)).collect();
                let ref_q: Vec<i16> = f
                    .iter()
                    .enumerate()
                    .map(|(k, &x)| params.quantize(x, k % 3))
                    .collect();
                assert_eq!(want.2, ref_q);
                let ref_h: Vec<u16> = f
                    .iter()
                    .map(|&x| half::f16::from_f32(x).to_bits())
                    .collect();
                assert_eq!(want.1, ref_h);
                if x86::has_avx2() {
                    assert_eq!(
                        stage::<Avx2>(&src, normals, &q),
                        want,
                        "avx2, round {round}"
                    );
                } else {
                    eprintln!("avx2 part skipped: this CPU has no AVX2+FMA");
                }
                if x86::has_avx512() {
                    assert_eq!(
                        stage::<Avx512>(&src, normals, &q),
                        want,
                        "avx512, round {round}"
                    );
                } else {
                    eprintln!("avx512 part skipped: this CPU has no AVX-512F");
                }
            }
        }
    }

    #[test]
    fn interleave_puts_vertex_components_together() {
        let src: [f32; 48] = std::array::from_fn(|i| i as f32);
        let q = Q16Pattern::new(&Q16Params::new(Quantization::default(), true));
        let (f, _, _) = stage::<Portable>(&src, false, &q);
        let want: Vec<u32> = (0..48)
            .map(|k| ((k % 3) * 16 + k / 3) as f32)
            .map(f32::to_bits)
            .collect();
        assert_eq!(f, want);
    }
}
