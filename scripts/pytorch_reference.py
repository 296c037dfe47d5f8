"""PyTorch on the same work as `learner bench`'s training step (compared in docs/benchmarks.md).

DeepRacer's camera networks (160x120 grey frames): SHALLOW (conv 32x8/4, 64x4/2, 64x3/1,
dense 512), DEEP and DEEPER as `policy::model` builds them; separate policy (5 actions) and
value towers, minibatch 64: forward, PPO's clipped loss plus the value loss, backward, and one
Adam step. Prints sample-gradients/s per thread count on the CPU, or on a CUDA GPU
(`--device cuda`: the batch resident there, f32 with TF32 off, as Paddock's kernels compute),
and with `--gemm` cuBLAS's rate on one big f32 product, the library's ceiling beside the
figure `learner bench --device gpu` prints for Paddock's own GEMM kernel.

    python3 scripts/pytorch_reference.py --seconds 4 --threads 1 2
    python3 scripts/pytorch_reference.py --device cuda --network SHALLOW DEEP DEEPER --gemm
"""
import argparse
import time

import torch
import torch.nn as nn

# (filters, kernel, stride) of each conv layer, then the dense layers, per network.
NETWORKS = {
    "SHALLOW": ([(32, 8, 4), (64, 4, 2), (64, 3, 1)], [512]),
    "DEEP": ([(32, 5, 2), (32, 3, 1), (64, 3, 2), (64, 3, 1), (64, 1, 1)], [512]),
    "DEEPER": ([(32, 8, 4), (32, 4, 2), (64, 4, 2), (64, 3, 1), (512, 1, 1), (512, 1, 1)], [256, 128]),
}


def tower(network, out):
    convs, dense = NETWORKS[network]
    layers, c = [], 1
    for f, k, s in convs:
        layers += [nn.Conv2d(c, f, k, s), nn.ReLU()]
        c = f
    layers.append(nn.Flatten())
    for d in dense:
        layers += [nn.LazyLinear(d), nn.ReLU()]
    layers.append(nn.LazyLinear(out))
    return nn.Sequential(*layers)


def sync(device):
    if device == "cuda":
        torch.cuda.synchronize()


def measure(network, device, threads, seconds, batch, adam):
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    obs = (torch.rand(batch, 1, 120, 160) * 255.0).to(device)
    pi, v = tower(network, 5).to(device), tower(network, 1).to(device)
    with torch.no_grad():
        pi(obs / 255.0)
        v(obs / 255.0)
    params = list(pi.parameters()) + list(v.parameters())
    opt = torch.optim.Adam(params, lr=3e-4)
    act = torch.randint(0, 5, (batch,), device=device)
    old_logp = torch.full((batch,), -1.6, device=device)
    adv = torch.randn(batch, device=device)
    ret = torch.randn(batch, device=device)

    def step():
        x = obs / 255.0
        logp = torch.log_softmax(pi(x), dim=1).gather(1, act[:, None])[:, 0]
        ratio = torch.exp(logp - old_logp)
        surr = torch.min(ratio * adv, ratio.clamp(0.8, 1.2) * adv)
        value = v(x)[:, 0]
        loss = -surr.mean() + 0.5 * ((value - ret) ** 2).mean()
        opt.zero_grad(set_to_none=False)
        loss.backward()
        if adam:
            opt.step()

    for _ in range(3):
        step()
    sync(device)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(16):
            step()
        n += 16
        sync(device)
    return n * batch / (time.perf_counter() - t0)


def gemm_rate(side, seconds):
    """cuBLAS: side x side x side f32 products (TF32 off), TFLOP/s."""
    a = torch.full((side, side), 0.5, device="cuda")
    b = torch.full((side, side), 0.25, device="cuda")
    c = a @ b.T
    sync("cuda")
    assert c[-1, -1].item() == 0.125 * side
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(8):
            torch.mm(a, b.T, out=c)
        n += 8
        sync("cuda")
    return 2.0 * side**3 * n / (time.perf_counter() - t0) / 1e12


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--network", nargs="+", default=["SHALLOW"], choices=sorted(NETWORKS))
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gemm", action="store_true", help="cuBLAS's f32 rate on a 4096^3 product (cuda)")
    a = ap.parse_args()
    if a.device == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cudnn.benchmark = True
        where = torch.cuda.get_device_name()
        threads = a.threads[:1]
    else:
        where, threads = "CPU", a.threads
    for network in a.network:
        print(f"torch {torch.__version__}, {network} on {where}, both towers, minibatch {a.batch}")
        for t in threads:
            with_adam = measure(network, a.device, t, a.seconds, a.batch, True)
            without = measure(network, a.device, t, a.seconds, a.batch, False)
            label = "the GPU (f32, TF32 off)" if a.device == "cuda" else f"{t} thread(s)"
            print(f"{label}: forward + backward + Adam {with_adam:.0f} sample-gradients/s; "
                  f"without Adam {without:.0f}")
    if a.gemm and a.device == "cuda":
        print(f"cuBLAS, one 4096x4096x4096 f32 product at a time (TF32 off): {gemm_rate(4096, a.seconds):.2f} TFLOP/s")


if __name__ == "__main__":
    main()
