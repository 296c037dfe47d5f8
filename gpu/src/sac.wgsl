// SAC's per-transition arithmetic around its networks' passes, one thread a transition:
// learner::sac's `losses_and_grads_share`, line for line. The figures of a transition live
// in `cols`, one block of `cap` values per column (the COL_ constants, kernels.rs's `sac`
// module), so the networks' outputs are copied in and the gradients read out as blocks.

struct Sac {
    // Transitions in the batch; the length of a column block.
    n: u32,
    cap: u32,
    // The Q heads' input width less the two action values (the embedding's width).
    w: u32,
    // V's loss: 1 Huber, 0 squared error.
    huber: u32,
    gamma: f32,
    // The weight of a transition in the losses (1 / batch).
    inv: f32,
    alpha: f32,
    scale0: f32,
    scale1: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

const COL_REWARD: u32 = 0u;
const COL_DONE: u32 = 1u;
const COL_EPS: u32 = 2u;
const COL_VNEXT: u32 = 6u;
const COL_Q1: u32 = 7u;
const COL_Q2: u32 = 8u;
const COL_E1: u32 = 9u;
const COL_E2: u32 = 10u;
const COL_D1: u32 = 11u;
const COL_D2: u32 = 12u;
const COL_A: u32 = 13u;
const COL_LOGP: u32 = 15u;
const COL_Q1P: u32 = 16u;
const COL_Q2P: u32 = 17u;
const COL_MINQ: u32 = 18u;
const COL_DM1: u32 = 19u;
const COL_DM2: u32 = 20u;
const COL_V: u32 = 21u;
const COL_EV: u32 = 22u;
const COL_DV: u32 = 23u;

const LOG_STD_LO: f32 = -20.0;
const LOG_STD_HI: f32 = 2.0;
const HALF_LN_2PI: f32 = 0.9189385332046727;
const F32_EPSILON: f32 = 1.1920929e-7;

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read> c: array<f32>;
@group(0) @binding(3) var<storage, read_write> d: array<f32>;
@group(0) @binding(4) var<storage, read_write> cols: array<f32>;
@group(0) @binding(5) var<uniform> q: Sac;

fn at(col: u32, i: u32) -> u32 {
    return col * q.cap + i;
}

fn scale(k: u32) -> f32 {
    return select(q.scale1, q.scale0, k == 0u);
}

// The policy's draws (`a`: its outputs, two means then two log-stds a row): the action
// tanh(mean + exp(log σ)·ε) and log π, as policy::model::squashed.
@compute @workgroup_size(64, 1, 1)
fn draws(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= q.n) {
        return;
    }
    var logp = 0.0;
    for (var k = 0u; k < 2u; k++) {
        let ls = clamp(a[i * 4u + 2u + k], LOG_STD_LO, LOG_STD_HI);
        let e = cols[at(COL_EPS + k, i)];
        let u = a[i * 4u + k] + exp(ls) * e;
        // tanh saturates to ±1 in f32 beyond 9; a driver's exp-based tanh would overflow there.
        let act = clamp(select(tanh(u), sign(u), abs(u) > 9.0), -1.0, 1.0);
        let jac = clamp(scale(k) * (1.0 - act * act) + F32_EPSILON, 1e-10, 1.0);
        cols[at(COL_A + k, i)] = act;
        logp += -0.5 * e * e - ls - HALF_LN_2PI - log(jac);
    }
    cols[at(COL_LOGP, i)] = logp;
}

// The Q heads' errors against r + (1 − done)·γ·V_target(s'), and their gradients.
@compute @workgroup_size(64, 1, 1)
fn q_errors(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= q.n) {
        return;
    }
    let y = cols[at(COL_REWARD, i)] + (1.0 - cols[at(COL_DONE, i)]) * q.gamma * cols[at(COL_VNEXT, i)];
    let e1 = cols[at(COL_Q1, i)] - y;
    let e2 = cols[at(COL_Q2, i)] - y;
    cols[at(COL_E1, i)] = e1;
    cols[at(COL_E2, i)] = e2;
    cols[at(COL_D1, i)] = e1 * q.inv;
    cols[at(COL_D2, i)] = e2 * q.inv;
}

// min(q1, q2) at the policy's draws, and the gradient of −min wrt each head's output.
@compute @workgroup_size(64, 1, 1)
fn min_q(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= q.n) {
        return;
    }
    let q1 = cols[at(COL_Q1P, i)];
    let q2 = cols[at(COL_Q2P, i)];
    let first = q1 <= q2;
    cols[at(COL_MINQ, i)] = min(q1, q2);
    cols[at(COL_DM1, i)] = select(0.0, -q.inv, first);
    cols[at(COL_DM2, i)] = select(-q.inv, 0.0, first);
}

// The policy's output gradient (`d`, four a row) from its outputs (`a`), the heads' input
// gradients at the draws (`b`, `c`: w + 2 a row, the action last) and the draws.
@compute @workgroup_size(64, 1, 1)
fn policy_grad(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= q.n) {
        return;
    }
    let width = q.w + 2u;
    for (var k = 0u; k < 2u; k++) {
        let act = cols[at(COL_A + k, i)];
        let slope = 1.0 - act * act;
        let jac = scale(k) * slope + F32_EPSILON;
        var d_corr = 0.0;
        if (jac > 1e-10 && jac < 1.0) {
            d_corr = 2.0 * act * scale(k) * slope / jac;
        }
        let dq_da = b[i * width + q.w + k] + c[i * width + q.w + k];
        let d_u = q.alpha * q.inv * d_corr + dq_da * slope;
        let ls = a[i * 4u + 2u + k];
        d[i * 4u + k] = d_u;
        var d_ls = 0.0;
        if (ls > LOG_STD_LO && ls < LOG_STD_HI) {
            d_ls = -q.alpha * q.inv + d_u * exp(ls) * cols[at(COL_EPS + k, i)];
        }
        d[i * 4u + 2u + k] = d_ls;
    }
}

// V's error against min q − α·log π of the same draws, and its gradient.
@compute @workgroup_size(64, 1, 1)
fn v_errors(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= q.n) {
        return;
    }
    let e = cols[at(COL_V, i)] - (cols[at(COL_MINQ, i)] - q.alpha * cols[at(COL_LOGP, i)]);
    cols[at(COL_EV, i)] = e;
    if (q.huber == 1u) {
        cols[at(COL_DV, i)] = clamp(e, -1.0, 1.0) * q.inv;
    } else {
        cols[at(COL_DV, i)] = 2.0 * e * q.inv;
    }
}
