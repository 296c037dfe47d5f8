// C (m×n, row-major) = op(A) (m×k) · op(B) (k×n), + C when asked. A is stored m×k, or k×m
// when transposed; B k×n, or n×k when transposed; each from an offset in its buffer.
//
// A workgroup makes a 64×64 block of C, each of its 16×16 threads a 4×4 piece, through
// 16-deep slices of A and B staged in workgroup memory. Split over K (workgroup_id.z) each
// workgroup sums its own range of K into its own copy of C, and `reduce` adds the copies.

struct Gemm {
    m: u32,
    n: u32,
    k: u32,
    // bit 0: A transposed; bit 1: B transposed; bit 2: add to C.
    flags: u32,
    a_off: u32,
    b_off: u32,
    c_off: u32,
    // K per split (= k when not split); C's copies are `c_stride` apart.
    k_chunk: u32,
    c_stride: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read_write> c: array<f32>;
@group(0) @binding(3) var<uniform> p: Gemm;

var<workgroup> ta: array<f32, 1024>;
var<workgroup> tb: array<f32, 1024>;

fn load_a(i: u32, q: u32, k_end: u32) -> f32 {
    if (i >= p.m || q >= k_end) {
        return 0.0;
    }
    if ((p.flags & 1u) != 0u) {
        return a[p.a_off + q * p.m + i];
    }
    return a[p.a_off + i * p.k + q];
}

fn load_b(q: u32, j: u32, k_end: u32) -> f32 {
    if (q >= k_end || j >= p.n) {
        return 0.0;
    }
    if ((p.flags & 2u) != 0u) {
        return b[p.b_off + j * p.k + q];
    }
    return b[p.b_off + q * p.n + j];
}

@compute @workgroup_size(16, 16, 1)
fn gemm(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let row0 = wg.y * 64u;
    let col0 = wg.x * 64u;
    let t = l.y * 16u + l.x;
    let k_begin = wg.z * p.k_chunk;
    let k_end = min(p.k, k_begin + p.k_chunk);
    // Loads: A's slice as [q][row], B's as [q][col]; consecutive threads take consecutive
    // elements of whichever side is contiguous in memory.
    let a_t = (p.flags & 1u) != 0u;
    let b_t = (p.flags & 2u) != 0u;
    var acc: array<f32, 16>;
    for (var i = 0u; i < 16u; i++) {
        acc[i] = 0.0;
    }
    for (var k0 = k_begin; k0 < k_end; k0 += 16u) {
        for (var e = 0u; e < 4u; e++) {
            let idx = t + e * 256u;
            var q: u32;
            var r: u32;
            if (a_t) {
                q = idx / 64u;
                r = idx % 64u;
            } else {
                q = idx % 16u;
                r = idx / 16u;
            }
            ta[q * 64u + r] = load_a(row0 + r, k0 + q, k_end);
            if (b_t) {
                q = idx % 16u;
                r = idx / 16u;
            } else {
                q = idx / 64u;
                r = idx % 64u;
            }
            tb[q * 64u + r] = load_b(k0 + q, col0 + r, k_end);
        }
        workgroupBarrier();
        for (var q = 0u; q < 16u; q++) {
            var av: array<f32, 4>;
            var bv: array<f32, 4>;
            for (var r = 0u; r < 4u; r++) {
                av[r] = ta[q * 64u + l.y * 4u + r];
                bv[r] = tb[q * 64u + l.x * 4u + r];
            }
            for (var r = 0u; r < 4u; r++) {
                for (var s = 0u; s < 4u; s++) {
                    acc[r * 4u + s] += av[r] * bv[s];
                }
            }
        }
        workgroupBarrier();
    }
    let add = (p.flags & 4u) != 0u;
    for (var r = 0u; r < 4u; r++) {
        let i = row0 + l.y * 4u + r;
        for (var s = 0u; s < 4u; s++) {
            let j = col0 + l.x * 4u + s;
            if (i < p.m && j < p.n) {
                let at = p.c_off + wg.z * p.c_stride + i * p.n + j;
                if (add) {
                    c[at] = c[at] + acc[r * 4u + s];
                } else {
                    c[at] = acc[r * 4u + s];
                }
            }
        }
    }
}

// C[c_off + i] (+)= Σ_z parts[z·m·n + i]: the copies of a split product, added in order.
@compute @workgroup_size(256, 1, 1)
fn reduce(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = (wg.y * nw.x + wg.x) * 256u + l.x;
    let mn = p.m * p.n;
    if (i >= mn) {
        return;
    }
    var s = 0.0;
    for (var z = 0u; z < p.k; z++) {
        s += a[z * mn + i];
    }
    let at = p.c_off + i;
    if ((p.flags & 4u) != 0u) {
        c[at] = c[at] + s;
    } else {
        c[at] = s;
    }
}
