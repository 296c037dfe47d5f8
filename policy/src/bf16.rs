//! Matrix products with bf16 operands and f32 sums, for CPUs with AVX-512's bf16 dot product
//! (`vdpbf16ps`: AMD Zen 4 and later, Intel Cooper Lake, Sapphire Rapids and later), where it
//! makes twice the multiply-adds of an f32 FMA a cycle. Operands are rounded to bf16 (to
//! nearest, ties to even) as they are packed; products of two bf16 values are exact in f32,
//! and every sum is an f32 sum in a fixed order: along `k`, a pair of terms at a time. Each
//! output is made by one thread whatever the thread count, so a product gives the same bits on
//! one thread and on many.
//!
//! No well-kept Rust library makes this product: faer and `gemm` take f16 by widening it to
//! f32, and gemmkit's bf16 product writes bf16 results where a gradient needs f32 ones.
//!
//! The one module of the workspace with `unsafe` code: the intrinsics' loads and stores take
//! pointers. Every entry asserts the operands' lengths against the shape and that the CPU has
//! the features; every pointer stays inside those slices (masked loads and stores at the
//! edges). Tests compare the products with a reference over shapes that hit every edge.
#![allow(unsafe_code)]

use faer::Par;
#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;
use std::cell::RefCell;

/// Rows of the result a micro-kernel makes at once.
const MR: usize = 12;
/// Columns of the result a micro-kernel makes at once (two vectors of 16).
const NR: usize = 32;
/// Columns of the result a block of `b` covers, so that the block stays in L2.
const NC: usize = 1024;

/// Whether this CPU makes the product (checked once).
pub fn available() -> bool {
    static HAS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *HAS.get_or_init(|| {
        is_x86_feature_detected!("avx512f")
            && is_x86_feature_detected!("avx512bw")
            && is_x86_feature_detected!("avx512vl")
            && is_x86_feature_detected!("avx512bf16")
    })
}

/// `x` rounded to bf16, to nearest with ties to even (NaN stays NaN), as its 16 bits.
pub fn round(x: f32) -> u16 {
    half::bf16::from_f32(x).to_bits()
}

/// A matrix operand: row-major storage, possibly transposed.
#[derive(Clone, Copy)]
struct View<'a> {
    data: &'a [f32],
    /// Stored as `cols × rows` (the operand is the storage's transpose).
    t: bool,
    rows: usize,
    cols: usize,
}

thread_local! {
    /// The packed operands' buffers, kept between calls (a training step allocates nothing).
    static PACKS: RefCell<(Vec<u32>, Vec<u32>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

/// `dst = op(a) · op(b)` (+ `dst`) as `p` describes, all row-major as [`crate::nn::gemm`]
/// takes them. Panics unless [`available`].
pub fn gemm(dst: &mut [f32], a: &[f32], b: &[f32], p: crate::nn::Product, par: Par) {
    let crate::nn::Product { m, n, k, a_t, b_t, add } = p;
    assert!(available(), "bf16 products need AVX-512 BF16");
    assert_eq!(dst.len(), m * n);
    assert_eq!(a.len(), m * k);
    assert_eq!(b.len(), k * n);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !add {
            dst.fill(0.0);
        }
        return;
    }
    let a = View { data: a, t: a_t, rows: m, cols: k };
    let b = View { data: b, t: b_t, rows: k, cols: n };
    // k in blocks of `kp` pairs: a block of b (kp pairs × up to NC columns) stays in L2.
    let nc = n.min(NC).next_multiple_of(NR);
    let kp = (65536 / nc).clamp(64, 512).min(k.div_ceil(2));
    let threads = par.degree().max(1);
    let col_blocks = n.div_ceil(NC);
    let dst_addr = dst.as_mut_ptr() as usize;
    // One column block: its k blocks in turn, each packed once, its row tiles split between
    // the threads when there are more threads than column blocks.
    let block = |jb: usize, tile_par: bool| {
        let j0 = jb * NC;
        let j1 = (j0 + NC).min(n);
        let panels = (j1 - j0).div_ceil(NR);
        for (kb, k0) in (0..k).step_by(2 * kp).enumerate() {
            let k1 = (k0 + 2 * kp).min(k);
            let pairs = (k1 - k0).div_ceil(2);
            let accumulate = add || kb > 0;
            let tiles = m.div_ceil(MR);
            let mut bp = PACKS.with(|p| std::mem::take(&mut p.borrow_mut().1));
            bp.clear();
            bp.resize(panels * pairs * NR, 0);
            if tile_par && panels > 1 {
                use rayon::prelude::*;
                bp.par_chunks_mut(pairs * NR).enumerate().for_each(|(p, panel)| {
                    let c0 = j0 + p * NR;
                    // SAFETY: `available()` was asserted.
                    unsafe { pack_b(&b, k0, k1, c0, (c0 + NR).min(j1), panel) }
                });
            } else {
                // SAFETY: `available()` was asserted.
                unsafe { pack_b(&b, k0, k1, j0, j1, &mut bp) };
            }
            let run_tiles = |t0: usize, t1: usize| {
                let mut ap = PACKS.with(|p| std::mem::take(&mut p.borrow_mut().0));
                ap.clear();
                ap.resize(MR * a_stride(pairs), 0);
                for t in t0..t1 {
                    let i0 = t * MR;
                    let i1 = (i0 + MR).min(m);
                    // SAFETY: `available()` was asserted; each (tile, panel) of `dst` is written
                    // by one thread at a time, within `dst`'s bounds (checked by the masks).
                    unsafe {
                        let (rs, ks) = pack_a(&a, i0, i1, k0, k1, &mut ap);
                        for p in 0..panels {
                            let c0 = j0 + p * NR;
                            let nr = (j1 - c0).min(NR);
                            let c = (dst_addr as *mut f32).add(i0 * n + c0);
                            kernel(Tile {
                                pairs,
                                a: ap.as_ptr(),
                                rs,
                                ks,
                                b: bp.as_ptr().add(p * pairs * NR),
                                c,
                                ldc: n,
                                mr: i1 - i0,
                                nr,
                                accumulate,
                            });
                        }
                    }
                }
                PACKS.with(|p| p.borrow_mut().0 = ap);
            };
            if tile_par && tiles > 1 {
                use rayon::prelude::*;
                let per = tiles.div_ceil(threads);
                (0..tiles.div_ceil(per)).into_par_iter().for_each(|g| run_tiles(g * per, ((g + 1) * per).min(tiles)));
            } else {
                run_tiles(0, tiles);
            }
            PACKS.with(|p| p.borrow_mut().1 = bp);
        }
    };
    if threads > 1 && col_blocks >= threads {
        use rayon::prelude::*;
        (0..col_blocks).into_par_iter().for_each(|jb| block(jb, false));
    } else {
        for jb in 0..col_blocks {
            block(jb, threads > 1);
        }
    }
}

/// Pack rows `i0..i1` and columns `k0..k1` of `a` as bf16 pairs along k, zero-padded to MR rows
/// and whole pairs; returns the strides (in pairs) between rows and between pairs.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
unsafe fn pack_a(a: &View, i0: usize, i1: usize, k0: usize, k1: usize, out: &mut [u32]) -> (usize, usize) {
    // SAFETY: the caller checked the CPU's features; pointers stay within the slices
    // they come from (bounds above, masks at the edges).
    unsafe {
        let pairs = (k1 - k0).div_ceil(2);
        if !a.t {
            // Rows a cache line apart beyond whole lines, so that the kernel's MR streams do not
            // fall in one L1 set.
            let rs = a_stride(pairs);
            // Row by row: a row's k run is contiguous; 16 values at a time become 8 pairs.
            for r in 0..MR {
                let row = &mut out[r * rs..r * rs + pairs];
                if i0 + r >= i1 {
                    row.fill(0);
                    continue;
                }
                let src = &a.data[(i0 + r) * a.cols + k0..(i0 + r) * a.cols + k1];
                let dst = row.as_mut_ptr() as *mut u16;
                let mut c = 0;
                while c + 16 <= src.len() {
                    let v = _mm512_loadu_ps(src.as_ptr().add(c));
                    let h: __m256i = std::mem::transmute(_mm512_cvtneps_pbh(v));
                    _mm256_storeu_si256(dst.add(c) as *mut __m256i, h);
                    c += 16;
                }
                if c < src.len() {
                    let rest = src.len() - c;
                    let mask = (1u16 << rest) - 1;
                    let v = _mm512_maskz_loadu_ps(mask, src.as_ptr().add(c));
                    let h: __m256i = std::mem::transmute(_mm512_cvtneps_pbh(v));
                    // Up to the end of the row's pairs (a zero for the odd k's missing partner).
                    let len = (2 * pairs - c) as u32;
                    _mm256_mask_storeu_epi16(dst.add(c) as *mut i16, ((1u32 << len) - 1) as u16, h);
                }
            }
            (rs, 1)
        } else {
            // Pair by pair: rows k and k+1 of the storage hold the tile's MR values contiguously.
            let mr = i1 - i0;
            let mask = ((1u32 << mr) - 1) as u16;
            for p in 0..pairs {
                let k = k0 + 2 * p;
                let lo = _mm512_maskz_loadu_ps(mask, a.data.as_ptr().add(k * a.rows + i0));
                let hi = if k + 1 < k1 {
                    _mm512_maskz_loadu_ps(mask, a.data.as_ptr().add((k + 1) * a.rows + i0))
                } else {
                    _mm512_setzero_ps()
                };
                let v = interleave(lo, hi);
                _mm512_mask_storeu_epi32(out.as_mut_ptr().add(p * MR) as *mut i32, ((1u32 << MR) - 1) as u16, v);
            }
            (1, MR)
        }
    }
}

/// The distance in pairs between the rows of a packed tile of `a` with `pairs` pairs a row.
fn a_stride(pairs: usize) -> usize {
    pairs.next_multiple_of(16) + 16
}

/// 16 pairs `(lo[i], hi[i])` as bf16, `lo` in the low half of each 32 bits.
#[inline]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
fn interleave(lo: __m512, hi: __m512) -> __m512i {
    // SAFETY: plain register conversions.
    let (l, h): (__m256i, __m256i) = unsafe {
        (
            std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(lo)),
            std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(hi)),
        )
    };
    _mm512_or_si512(_mm512_cvtepu16_epi32(l), _mm512_slli_epi32::<16>(_mm512_cvtepu16_epi32(h)))
}

/// Pack rows `k0..k1` and columns `j0..j1` of `b` as panels of NR columns, each pair of k a
/// row of NR bf16 pairs, into `out` as the caller zeroed it (the padding past `j1` stays zero).
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
unsafe fn pack_b(b: &View, k0: usize, k1: usize, j0: usize, j1: usize, out: &mut [u32]) {
    // SAFETY: the caller checked the CPU's features; pointers stay within the slices
    // they come from (bounds above, masks at the edges).
    unsafe {
        let pairs = (k1 - k0).div_ceil(2);
        let panels = (j1 - j0).div_ceil(NR);
        for p in 0..panels {
            let c0 = j0 + p * NR;
            let nr = (j1 - c0).min(NR);
            let panel = &mut out[p * pairs * NR..(p + 1) * pairs * NR];
            if !b.t {
                for q in 0..pairs {
                    let k = k0 + 2 * q;
                    for half in 0..2 {
                        let c = c0 + 16 * half;
                        let w = nr.saturating_sub(16 * half).min(16);
                        let dst = panel.as_mut_ptr().add(q * NR + 16 * half) as *mut i32;
                        if w == 0 {
                            _mm512_storeu_si512(dst as *mut __m512i, _mm512_setzero_si512());
                            continue;
                        }
                        let mask = ((1u32 << w) - 1) as u16;
                        let lo = _mm512_maskz_loadu_ps(mask, b.data.as_ptr().add(k * b.cols + c));
                        let hi = if k + 1 < k1 {
                            _mm512_maskz_loadu_ps(mask, b.data.as_ptr().add((k + 1) * b.cols + c))
                        } else {
                            _mm512_setzero_ps()
                        };
                        _mm512_storeu_si512(dst as *mut __m512i, interleave(lo, hi));
                    }
                }
            } else {
                // Column by column: a column's k run is contiguous in the storage; 32 values at a
                // time become 16 pairs, scattered down the panel's column (the columns past `nr`
                // stay as the caller zeroed them).
                let idx = _mm512_mullo_epi32(
                    _mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0),
                    _mm512_set1_epi32(NR as i32),
                );
                for j in 0..nr {
                    let src = &b.data[(c0 + j) * b.rows + k0..(c0 + j) * b.rows + k1];
                    let col = panel.as_mut_ptr().add(j);
                    let mut q = 0;
                    while 2 * q + 32 <= src.len() {
                        let lo = _mm512_loadu_ps(src.as_ptr().add(2 * q));
                        let hi = _mm512_loadu_ps(src.as_ptr().add(2 * q + 16));
                        let v: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(hi, lo));
                        _mm512_i32scatter_epi32::<4>(col.add(q * NR) as *mut i32, idx, v);
                        q += 16;
                    }
                    while q < pairs {
                        let lo = src[2 * q];
                        let hi = src.get(2 * q + 1).copied().unwrap_or(0.0);
                        *col.add(q * NR) = round(lo) as u32 | (round(hi) as u32) << 16;
                        q += 1;
                    }
                }
            }
        }
    }
}

/// One micro-kernel call: `c (mr×nr, row stride ldc) (+)= Σ over `pairs` of a's pair (row r:
/// `a[r·rs + q·ks]`) times the panel `b`'s row `q`; `accumulate`: add into `c`.
struct Tile {
    pairs: usize,
    a: *const u32,
    rs: usize,
    ks: usize,
    b: *const u32,
    c: *mut f32,
    ldc: usize,
    mr: usize,
    nr: usize,
    accumulate: bool,
}

/// Run `t` (see [`Tile`]).
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512bf16")]
unsafe fn kernel(t: Tile) {
    let Tile { pairs, a, rs, ks, b, c, ldc, mr, nr, accumulate } = t;
    // SAFETY: the caller checked the CPU's features; pointers stay within the slices
    // they come from (bounds above, masks at the edges).
    unsafe {
        let mut acc = [[_mm512_setzero_ps(); 2]; MR];
        for q in 0..pairs {
            let b0: __m512bh = std::mem::transmute(_mm512_loadu_si512(b.add(q * NR) as *const __m512i));
            let b1: __m512bh = std::mem::transmute(_mm512_loadu_si512(b.add(q * NR + 16) as *const __m512i));
            for (r, acc) in acc.iter_mut().enumerate() {
                let av: __m512bh = std::mem::transmute(_mm512_set1_epi32(*a.add(r * rs + q * ks) as i32));
                acc[0] = _mm512_dpbf16_ps(acc[0], av, b0);
                acc[1] = _mm512_dpbf16_ps(acc[1], av, b1);
            }
        }
        let m0 = if nr >= 16 { 0xFFFFu16 } else { ((1u32 << nr) - 1) as u16 };
        let m1 = if nr >= 32 {
            0xFFFFu16
        } else if nr > 16 {
            ((1u32 << (nr - 16)) - 1) as u16
        } else {
            0
        };
        for (r, acc) in acc.iter().enumerate().take(mr) {
            let row = c.add(r * ldc);
            let (mut v0, mut v1) = (acc[0], acc[1]);
            if accumulate {
                v0 = _mm512_add_ps(_mm512_maskz_loadu_ps(m0, row), v0);
                v1 = _mm512_add_ps(_mm512_maskz_loadu_ps(m1, row.add(16)), v1);
            }
            _mm512_mask_storeu_ps(row, m0, v0);
            _mm512_mask_storeu_ps(row.add(16), m1, v1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `x` as the f64 of its bf16 rounding.
    fn r(x: f32) -> f64 {
        f32::from_bits((round(x) as u32) << 16) as f64
    }

    /// Issue 55: the bf16 product agrees with the product of the rounded operands summed in
    /// f64, to f32's rounding of the sum, for every storage order, with and without adding
    /// into the output, over shapes that leave partial tiles, panels, pairs and k blocks and
    /// span several column blocks; and a product gives the same bits on one thread and two.
    #[test]
    fn products_match_the_rounded_operands_sum_and_do_not_depend_on_threads() {
        if !available() {
            // Nothing to check here: `nn::gemm_in`'s test checks that such a CPU is given f32.
            return;
        }
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut rnd = move || rng.random_range(-0.5f32..0.5);
        // (m, n, k)
        let shapes = [
            (1, 1, 1),
            (1, 17, 3),
            (13, 33, 2),
            (12, 32, 64),
            (25, 47, 129),
            (37, 45, 1025),
            (64, 2100, 70),
            (130, 64, 2500),
        ];
        for (m, n, k) in shapes {
            for (a_t, b_t, add) in
                [(false, false, false), (true, false, true), (false, true, true), (true, true, false)]
            {
                let a: Vec<f32> = (0..m * k).map(|_| rnd()).collect();
                let b: Vec<f32> = (0..k * n).map(|_| rnd()).collect();
                let c0: Vec<f32> = (0..m * n).map(|_| rnd()).collect();
                let mut one = c0.clone();
                gemm(&mut one, &a, &b, crate::nn::Product { m, n, k, a_t, b_t, add }, Par::Seq);
                let mut two = c0.clone();
                gemm(&mut two, &a, &b, crate::nn::Product { m, n, k, a_t, b_t, add }, Par::rayon(2));
                let what = format!("{m}×{n}×{k}, a_t {a_t}, b_t {b_t}, add {add}");
                assert!(one.iter().zip(&two).all(|(x, y)| x.to_bits() == y.to_bits()), "{what}: threads differ");
                for i in 0..m {
                    for j in 0..n {
                        let (mut sum, mut mag) =
                            if add { (c0[i * n + j] as f64, c0[i * n + j].abs() as f64) } else { (0.0, 0.0) };
                        for q in 0..k {
                            let x = if a_t { a[q * m + i] } else { a[i * k + q] };
                            let y = if b_t { b[j * k + q] } else { b[q * n + j] };
                            sum += r(x) * r(y);
                            mag += (r(x) * r(y)).abs();
                        }
                        let got = one[i * n + j] as f64;
                        // f32 sums: an error of a few units in the last place of the terms' magnitude.
                        assert!(
                            (got - sum).abs() <= 1e-6 * mag.max(1e-30) * (k as f64).sqrt().max(1.0),
                            "{what}: [{i}][{j}] is {got}, expected {sum}"
                        );
                    }
                }
            }
        }
    }

    /// Rounding to bf16: to nearest, ties to even, NaN kept.
    #[test]
    fn rounding_is_to_nearest_with_ties_to_even() {
        for (x, bits) in [
            (1.0f32, 0x3F80u16),
            (f32::from_bits(0x3F80_8000), 0x3F80), // a tie, down to the even
            (f32::from_bits(0x3F81_8000), 0x3F82), // a tie, up to the even
            (f32::from_bits(0x3F80_8001), 0x3F81),
            (-2.5, 0xC020),
            (f32::INFINITY, 0x7F80),
        ] {
            assert_eq!(round(x), bits, "{x}");
        }
        assert!(f32::from_bits((round(f32::NAN) as u32) << 16).is_nan());
    }
}
