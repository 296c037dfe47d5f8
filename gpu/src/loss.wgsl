// PPO's two losses (the clipped surrogate with the entropy bonus, and the value loss) and
// their gradients wrt the towers' outputs, one thread a sample: learner::ppo's arithmetic,
// line for line.

struct Loss {
    // Samples in the minibatch; the tower's outputs per sample.
    n: u32,
    dim: u32,
    // 0: categorical; 1: Gaussian (two means); value loss: 0 Huber, 1 squared error.
    kind: u32,
    // Where the minibatch's indices start in `idx`.
    idx_off: u32,
    beta: f32,
    inv_n: f32,
    clip: f32,
    log_std0: f32,
    log_std1: f32,
    // Dual clip: a negative advantage's surrogate is at least this many advantages (0: none).
    dual_clip: f32,
    _pad1: u32,
    _pad2: u32,
}

// A sample's record in `samples`: advantage, behaviour log-probability, return, then the
// action (a categorical choice's index as u32 bits, or the two continuous values), 0.
const SAMPLE: u32 = 6u;
// A sample's figures in `stats`: −min(surrogates) (or the value loss), entropy, the KL
// estimate's term, clipped (0/1), and the log-std's two gradient terms.
const STATS: u32 = 6u;

@group(0) @binding(0) var<storage, read> out: array<f32>;
@group(0) @binding(1) var<storage, read> samples: array<f32>;
@group(0) @binding(2) var<storage, read> idx: array<f32>;
@group(0) @binding(3) var<storage, read_write> d: array<f32>;
@group(0) @binding(4) var<storage, read_write> stats: array<f32>;
@group(0) @binding(5) var<uniform> q: Loss;

const LOG_STD_LO: f32 = -20.0;
const LOG_STD_HI: f32 = 3.0;
const HALF_LN_2PI: f32 = 0.9189385332046727;

@compute @workgroup_size(64, 1, 1)
fn policy_loss(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    if (k >= q.n) {
        return;
    }
    let i = bitcast<u32>(idx[q.idx_off + k]);
    let a = samples[i * SAMPLE];
    let logp_old = samples[i * SAMPLE + 1u];
    let row = k * q.dim;
    var logp: f32;
    var entropy: f32;
    // Categorical: log Σ exp of the logits (log p_j = z_j − lse).
    var lse = 0.0;
    var c = 0u;
    if (q.kind == 0u) {
        var mx = -3.4028235e38;
        for (var j = 0u; j < q.dim; j++) {
            mx = max(mx, out[row + j]);
        }
        var s = 0.0;
        for (var j = 0u; j < q.dim; j++) {
            s += exp(out[row + j] - mx);
        }
        lse = mx + log(s);
        var h = 0.0;
        for (var j = 0u; j < q.dim; j++) {
            let lp = out[row + j] - lse;
            h += exp(lp) * lp;
        }
        entropy = -h;
        c = bitcast<u32>(samples[i * SAMPLE + 3u]);
        logp = out[row + c] - lse;
    } else {
        let ls0 = clamp(q.log_std0, LOG_STD_LO, LOG_STD_HI);
        let ls1 = clamp(q.log_std1, LOG_STD_LO, LOG_STD_HI);
        let z0 = (samples[i * SAMPLE + 3u] - out[row]) / exp(ls0);
        let z1 = (samples[i * SAMPLE + 4u] - out[row + 1u]) / exp(ls1);
        logp = (-0.5 * z0 * z0 - ls0 - HALF_LN_2PI) + (-0.5 * z1 * z1 - ls1 - HALF_LN_2PI);
        entropy = (ls0 + HALF_LN_2PI + 0.5) + (ls1 + HALF_LN_2PI + 0.5);
    }
    let ratio = exp(logp - logp_old);
    let clipped = clamp(ratio, 1.0 - q.clip, 1.0 + q.clip);
    let s1 = ratio * a;
    let s2 = clipped * a;
    let floored = q.dual_clip > 0.0 && a < 0.0 && min(s1, s2) < q.dual_clip * a;
    let at = k * STATS;
    stats[at] = -select(min(s1, s2), q.dual_clip * a, floored);
    stats[at + 1u] = entropy;
    stats[at + 2u] = (ratio - 1.0) - (logp - logp_old);
    stats[at + 3u] = select(0.0, 1.0, abs(ratio - 1.0) > q.clip);
    stats[at + 4u] = 0.0;
    stats[at + 5u] = 0.0;
    var g_logp = 0.0;
    if (s1 <= s2 && !floored) {
        g_logp = -a * ratio * q.inv_n;
    }
    if (q.kind == 0u) {
        for (var j = 0u; j < q.dim; j++) {
            let lp = out[row + j] - lse;
            let pj = exp(lp);
            let onehot = select(0.0, 1.0, j == c);
            d[row + j] = g_logp * (onehot - pj) + q.beta * q.inv_n * pj * (lp + entropy);
        }
    } else {
        let ls = array<f32, 2>(q.log_std0, q.log_std1);
        for (var j = 0u; j < 2u; j++) {
            let lsc = clamp(ls[j], LOG_STD_LO, LOG_STD_HI);
            let v = exp(2.0 * lsc);
            let diff = samples[i * SAMPLE + 3u + j] - out[row + j];
            d[row + j] = g_logp * diff / v;
            if (ls[j] > LOG_STD_LO && ls[j] < LOG_STD_HI) {
                stats[at + 4u + j] = g_logp * (diff * diff / v - 1.0);
            }
        }
    }
}

@compute @workgroup_size(64, 1, 1)
fn value_loss(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    if (k >= q.n) {
        return;
    }
    let i = bitcast<u32>(idx[q.idx_off + k]);
    let err = out[k] - samples[i * SAMPLE + 2u];
    var loss: f32;
    var g: f32;
    if (q.kind == 0u) {
        if (abs(err) <= 1.0) {
            loss = 0.5 * err * err;
            g = err;
        } else {
            loss = abs(err) - 0.5;
            g = sign(err);
        }
    } else {
        loss = err * err;
        g = 2.0 * err;
    }
    stats[k * STATS] = loss;
    d[k] = g * q.inv_n;
}
