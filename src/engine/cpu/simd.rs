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

/// Operations the kernels need on sixteen f32 lanes.
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
    /// Writes the first `n` (≤ 16) vertices given as x, y, z lanes to `out`, interleaved
    /// (x0 y0 z0 x1 ...).
    ///
    /// # Safety
    /// `out` must be valid for writing `3 * n` f32.
    unsafe fn store_xyz(x: Self, y: Self, z: Self, out: *mut f32, n: usize);
    /// Copies `n` floats from `src` to `dst` bypassing the caches where the ISA can (streaming
    /// stores skip the read-for-ownership of lines that are about to be overwritten whole).
    /// Callers must run [`Lanes::fence`] before other threads may read `dst`.
    ///
    /// # Safety
    /// `src` must be readable and `dst` writable for `n` floats; they must not overlap.
    unsafe fn copy_out(dst: *mut f32, src: *const f32, n: usize) {
        // SAFETY: forwarded from the caller.
        unsafe { std::ptr::copy_nonoverlapping(src, dst, n) }
    }
    /// Converts `n` floats from `src` to binary16 (round to nearest even) at `dst`.
    ///
    /// # Safety
    /// `src` must be readable and `dst` writable for `n` elements.
    unsafe fn copy_out_f16(dst: *mut half::f16, src: *const f32, n: usize) {
        // SAFETY: forwarded from the caller.
        unsafe {
            for i in 0..n {
                *dst.add(i) = half::f16::from_f32(*src.add(i));
            }
        }
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
    unsafe fn splat(x: f32) -> Self {
        Portable([x; LANES])
    }
    #[inline(always)]
    unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self {
        let mut r = c.0;
        for ((r, a), b) in r.iter_mut().zip(a.0).zip(b.0) {
            *r += a * b;
        }
        Portable(r)
    }
    #[inline(always)]
    unsafe fn store_xyz(x: Self, y: Self, z: Self, out: *mut f32, n: usize) {
        for i in 0..n.min(LANES) {
            // SAFETY: the caller guarantees 3n writable floats.
            unsafe {
                *out.add(3 * i) = x.0[i];
                *out.add(3 * i + 1) = y.0[i];
                *out.add(3 * i + 2) = z.0[i];
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
pub use x86::{Avx2, Avx512};

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{LANES, Lanes, Portable};
    use std::arch::x86_64::*;

    /// AVX2 + FMA (+ F16C for binary16 output): sixteen lanes as two 256-bit halves.
    #[derive(Clone, Copy)]
    pub struct Avx2(__m256, __m256);

    /// Interleaves eight vertices' x, y, z into 24 floats at `out`.
    ///
    /// # Safety
    /// Requires AVX2; `out` must be valid for 24 writes.
    #[inline(always)]
    unsafe fn interleave8(x: __m256, y: __m256, z: __m256, out: *mut f32) {
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
            _mm256_storeu_ps(out, o0);
            _mm256_storeu_ps(out.add(8), o1);
            _mm256_storeu_ps(out.add(16), o2);
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
        unsafe fn store_xyz(x: Self, y: Self, z: Self, out: *mut f32, n: usize) {
            // SAFETY: AVX2 is available; the caller guarantees 3n writable floats.
            unsafe {
                if n == LANES {
                    interleave8(x.0, y.0, z.0, out);
                    interleave8(x.1, y.1, z.1, out.add(24));
                } else {
                    spill_and_store(&x, &y, &z, out, n);
                }
            }
        }
        #[inline(always)]
        unsafe fn copy_out_f16(dst: *mut half::f16, src: *const f32, n: usize) {
            // SAFETY: F16C is available (checked with AVX2); the caller guarantees the ranges.
            unsafe {
                let mut i = 0;
                while i + 8 <= n {
                    let h =
                        _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(_mm256_loadu_ps(src.add(i)));
                    _mm_storeu_si128(dst.add(i).cast(), h);
                    i += 8;
                }
                Portable::copy_out_f16(dst.add(i), src.add(i), n - i);
            }
        }
        #[inline(always)]
        unsafe fn copy_out(dst: *mut f32, src: *const f32, n: usize) {
            // SAFETY: AVX is available; the caller guarantees the ranges.
            unsafe { stream_copy::<8>(dst, src, n, |d, s| _mm256_stream_ps(d, _mm256_loadu_ps(s))) }
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
        unsafe fn store_xyz(x: Self, y: Self, z: Self, out: *mut f32, n: usize) {
            if n < LANES {
                // SAFETY: forwarded from the caller.
                unsafe { spill_and_store(&x, &y, &z, out, n) };
                return;
            }
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
            // SAFETY: AVX-512F is available; the caller guarantees 48 writable floats.
            unsafe {
                for o in 0..3 {
                    let ixy = _mm512_loadu_si512(T.0[o].as_ptr().cast());
                    let iz = _mm512_loadu_si512(T.1[o].as_ptr().cast());
                    let t = _mm512_permutex2var_ps(x.0, ixy, y.0);
                    let r = _mm512_permutex2var_ps(t, iz, z.0);
                    _mm512_storeu_ps(out.add(16 * o), r);
                }
            }
        }
        #[inline(always)]
        unsafe fn copy_out_f16(dst: *mut half::f16, src: *const f32, n: usize) {
            // SAFETY: AVX-512F is available; the caller guarantees the ranges.
            unsafe {
                let mut i = 0;
                while i + 16 <= n {
                    let h = _mm512_cvtps_ph::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
                        _mm512_loadu_ps(src.add(i)),
                    );
                    _mm256_storeu_si256(dst.add(i).cast(), h);
                    i += 16;
                }
                Portable::copy_out_f16(dst.add(i), src.add(i), n - i);
            }
        }
        #[inline(always)]
        unsafe fn copy_out(dst: *mut f32, src: *const f32, n: usize) {
            // SAFETY: AVX-512F is available; the caller guarantees the ranges.
            unsafe {
                stream_copy::<16>(dst, src, n, |d, s| _mm512_stream_ps(d, _mm512_loadu_ps(s)))
            }
        }
        #[inline(always)]
        unsafe fn fence() {
            // SAFETY: SSE is part of x86-64.
            unsafe { _mm_sfence() }
        }
    }

    /// Copies with plain stores up to the first `W`-float aligned address of `dst`, streams
    /// whole aligned vectors, and finishes the tail with plain stores.
    ///
    /// # Safety
    /// `src` readable and `dst` writable for `n` floats, not overlapping; `stream(d, s)` must
    /// be a streaming store of `W` floats from `s` to `W * 4`-byte aligned `d`.
    #[inline(always)]
    unsafe fn stream_copy<const W: usize>(
        dst: *mut f32,
        src: *const f32,
        n: usize,
        stream: impl Fn(*mut f32, *const f32),
    ) {
        // SAFETY: every access stays inside the caller's ranges.
        unsafe {
            let misalign = (dst as usize / 4) % W;
            let head = if misalign == 0 {
                0
            } else {
                (W - misalign).min(n)
            };
            std::ptr::copy_nonoverlapping(src, dst, head);
            let mut i = head;
            while i + W <= n {
                stream(dst.add(i), src.add(i));
                i += W;
            }
            std::ptr::copy_nonoverlapping(src.add(i), dst.add(i), n - i);
        }
    }

    /// Partial tiles (at most one per rig): spill to arrays and store the valid vertices.
    ///
    /// # Safety
    /// `out` must be valid for writing `3 * n` f32.
    #[inline(never)]
    unsafe fn spill_and_store<L: Copy>(x: &L, y: &L, z: &L, out: *mut f32, n: usize) {
        debug_assert_eq!(size_of::<L>(), LANES * 4);
        // SAFETY: every implementation is exactly sixteen f32 lanes (checked above in debug);
        // reading it as an array is a plain reinterpretation of initialised bytes.
        unsafe {
            let a = |v: &L| {
                Portable(std::ptr::read_unaligned(
                    (v as *const L).cast::<[f32; LANES]>(),
                ))
            };
            Portable::store_xyz(a(x), a(y), a(z), out, n);
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

    /// Name for logs and bench output.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Avx512 => "avx512",
            Isa::Avx2Fma => "avx2+fma",
            Isa::Portable => "portable",
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    #[repr(align(64))]
    struct A([f32; 48]);

    fn interleaved<L: Lanes>(n: usize) -> Vec<u32> {
        let src = A(std::array::from_fn(|i| i as f32));
        let mut out = [f32::NAN; 48];
        // SAFETY: callers check the features; src is aligned and holds 48 floats; out too.
        unsafe {
            let p = src.0.as_ptr();
            let (x, y, z) = (L::load(p), L::load(p.add(16)), L::load(p.add(32)));
            L::store_xyz(x, y, z, out.as_mut_ptr(), n);
        }
        out[..3 * n].iter().map(|v| v.to_bits()).collect()
    }

    fn to_f16<L: Lanes>(src: &[f32]) -> Vec<u16> {
        let mut out = vec![half::f16::ZERO; src.len()];
        // SAFETY: callers check the features; both buffers hold src.len() elements.
        unsafe { L::copy_out_f16(out.as_mut_ptr(), src.as_ptr(), src.len()) };
        out.iter().map(|h| h.to_bits()).collect()
    }

    #[test]
    fn f16_conversion_matches_half() {
        // Values around rounding boundaries, subnormals, overflow, and signs.
        let src: Vec<f32> = (0..1000)
            .map(|i| (i as f32 - 500.0) * 0.001_234_5 * (1.0 + (i % 7) as f32 * 1e3))
            .chain([65520.0, 1e-7, -1e-5, 0.0, -0.0, 1.0 + 1.0 / 2048.0])
            .collect();
        let want = to_f16::<Portable>(&src);
        if x86::has_avx2() {
            assert_eq!(to_f16::<Avx2>(&src), want);
        }
        if x86::has_avx512() {
            assert_eq!(to_f16::<Avx512>(&src), want);
        }
    }

    #[test]
    fn interleave_matches_portable() {
        for n in [16, 9, 1] {
            let want = interleaved::<Portable>(n);
            assert_eq!(
                want[..3],
                [0f32.to_bits(), 16f32.to_bits(), 32f32.to_bits()]
            );
            if x86::has_avx2() {
                assert_eq!(interleaved::<Avx2>(n), want, "avx2, n={n}");
            } else {
                eprintln!("avx2 part skipped: this CPU has no AVX2+FMA");
            }
            if x86::has_avx512() {
                assert_eq!(interleaved::<Avx512>(n), want, "avx512, n={n}");
            } else {
                eprintln!("avx512 part skipped: this CPU has no AVX-512F");
            }
        }
    }
}
