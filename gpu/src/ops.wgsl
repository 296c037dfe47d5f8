// The layers' element-wise kernels, the convolution's unfold (im2col) and fold (col2im), and
// the gather of a minibatch's rows. One thread an output element; a dispatch of more than
// 65,535 workgroups is laid out over x and y.

struct Args {
    // Elements to write.
    n: u32,
    u0: u32,
    u1: u32,
    u2: u32,
    u3: u32,
    u4: u32,
    u5: u32,
    u6: u32,
    x: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<storage, read> src: array<f32>;
@group(0) @binding(1) var<storage, read> src2: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;
@group(0) @binding(3) var<uniform> p: Args;

fn index(wg: vec3<u32>, nw: vec3<u32>, l: vec3<u32>) -> u32 {
    return (wg.y * nw.x + wg.x) * 256u + l.x;
}

// dst[i] = src[u0 + i % u1]: a layer's bias (u1 values from offset u0) on every row.
@compute @workgroup_size(256, 1, 1)
fn fill_rows(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        dst[i] = src[p.u0 + i % p.u1];
    }
}

// dst = max(src, 0).
@compute @workgroup_size(256, 1, 1)
fn relu(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        dst[i] = max(src[i], 0.0);
    }
}

// dst = src (the gradient) where src2 (the ReLU's output) is positive, else 0.
@compute @workgroup_size(256, 1, 1)
fn relu_back(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        dst[i] = select(0.0, src[i], src2[i] > 0.0);
    }
}

// dst = src · x.
@compute @workgroup_size(256, 1, 1)
fn scale(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        dst[i] = src[i] * p.x;
    }
}

// dst = 1.
@compute @workgroup_size(256, 1, 1)
fn ones(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        dst[i] = 1.0;
    }
}

// Rows of src (u0 values each) picked by the indices in src2 (u32 bits): dst's row r is
// src's row src2[u1 + r].
@compute @workgroup_size(256, 1, 1)
fn gather_rows(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        let r = i / p.u0;
        let j = i % p.u0;
        let row = bitcast<u32>(src2[p.u1 + r]);
        dst[i] = src[row * p.u0 + j];
    }
}

// The convolution's geometry: input u0 × u1 × u2 (h, w, c; NHWC), kernel u3, stride u4,
// output u5 × u6 (oh, ow). A column row is one output pixel's patch in (ky, kx, c) order.

// Unfold: dst[(pixel) · kkc + (ky·k + kx)·c + ci] = src[b, oy·s + ky, ox·s + kx, ci].
@compute @workgroup_size(256, 1, 1)
fn im2col(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i >= p.n) {
        return;
    }
    let c = p.u2;
    let k = p.u3;
    let kkc = k * k * c;
    let pixel = i / kkc;
    let e = i % kkc;
    let ci = e % c;
    let kx = (e / c) % k;
    let ky = e / (c * k);
    let per = p.u5 * p.u6;
    let b = pixel / per;
    let oy = (pixel % per) / p.u6;
    let ox = pixel % p.u6;
    let y = oy * p.u4 + ky;
    let x = ox * p.u4 + kx;
    dst[i] = src[((b * p.u0 + y) * p.u1 + x) * c + ci];
}

// Fold (the unfold's adjoint): dst[b, y, x, ci] = Σ of the column entries that read it.
@compute @workgroup_size(256, 1, 1)
fn col2im(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i >= p.n) {
        return;
    }
    let h = p.u0;
    let w = p.u1;
    let c = p.u2;
    let k = p.u3;
    let s = p.u4;
    let kkc = k * k * c;
    let ci = i % c;
    let x = (i / c) % w;
    let y = (i / (c * w)) % h;
    let b = i / (c * w * h);
    var sum = 0.0;
    for (var ky = 0u; ky < k; ky++) {
        if (y < ky || (y - ky) % s != 0u) {
            continue;
        }
        let oy = (y - ky) / s;
        if (oy >= p.u5) {
            continue;
        }
        for (var kx = 0u; kx < k; kx++) {
            if (x < kx || (x - kx) % s != 0u) {
                continue;
            }
            let ox = (x - kx) / s;
            if (ox >= p.u6) {
                continue;
            }
            let pixel = (b * p.u5 + oy) * p.u6 + ox;
            sum += src[pixel * kkc + (ky * k + kx) * c + ci];
        }
    }
    dst[i] = sum;
}

// Rows of the twin Q heads' input: a row of src (u0 values: the embedding) then u1 values
// read column-major from src2 (column j at u3 + j·u2, row r).
@compute @workgroup_size(256, 1, 1)
fn concat_rows(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        let width = p.u0 + p.u1;
        let r = i / width;
        let j = i % width;
        if (j < p.u0) {
            dst[i] = src[r * p.u0 + j];
        } else {
            dst[i] = src2[p.u3 + (j - p.u0) * p.u2 + r];
        }
    }
}

// The first u0 values of each row (u1 values apart) of src and src2, added.
@compute @workgroup_size(256, 1, 1)
fn add_cols(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        let at = (i / p.u0) * p.u1 + i % p.u0;
        dst[i] = src[at] + src2[at];
    }
}

// dst = x · src + (1 − x) · dst: a target network moved towards its network.
@compute @workgroup_size(256, 1, 1)
fn lerp(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        dst[i] = p.x * src[i] + (1.0 - p.x) * dst[i];
    }
}

// Columns: dst[r · u1 + u2 + c] = src[r · u3 + u4 + c] for c below u0 (an input's values out
// of a sample, or an embedder's output into its place beside the others).
@compute @workgroup_size(256, 1, 1)
fn copy_cols(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = index(wg, nw, l);
    if (i < p.n) {
        let r = i / p.u0;
        let c = i % p.u0;
        dst[r * p.u1 + p.u2 + c] = src[r * p.u3 + p.u4 + c];
    }
}
