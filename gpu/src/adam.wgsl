// Adam over a parameter vector: policy::nn::Adam's arithmetic, element by element.

struct Opt {
    n: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    b1: f32,
    b2: f32,
    eps: f32,
    // lr / (1 − β1ᵗ), and 1 / (1 − β2ᵗ).
    step: f32,
    inv_c2: f32,
    _pad3: u32,
    _pad4: u32,
    _pad5: u32,
}

@group(0) @binding(0) var<storage, read_write> params: array<f32>;
@group(0) @binding(1) var<storage, read_write> m1: array<f32>;
@group(0) @binding(2) var<storage, read_write> m2: array<f32>;
@group(0) @binding(3) var<storage, read> grad: array<f32>;
@group(0) @binding(4) var<storage, read_write> flag: array<atomic<u32>>;
@group(0) @binding(5) var<uniform> o: Opt;

// Adam; a gradient value that is infinite or NaN (exponent all ones) sets flag[0].
@compute @workgroup_size(256, 1, 1)
fn adam(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    let i = (wg.y * nw.x + wg.x) * 256u + l.x;
    if (i >= o.n) {
        return;
    }
    let g = grad[i];
    if ((bitcast<u32>(g) & 0x7f800000u) == 0x7f800000u) {
        atomicOr(&flag[0], 1u);
    }
    let m = o.b1 * m1[i] + (1.0 - o.b1) * g;
    let v = o.b2 * m2[i] + (1.0 - o.b2) * g * g;
    m1[i] = m;
    m2[i] = v;
    params[i] = params[i] - o.step * m / (sqrt(v * o.inv_c2) + o.eps);
}
