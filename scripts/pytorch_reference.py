"""PyTorch on the same work as `learner bench`'s training step (compared in docs/benchmarks.md).

DeepRacer's SHALLOW network (160x120 grey frames; conv 32x8/4, 64x4/2, 64x3/1, dense 512),
separate policy (10 actions) and value towers, minibatch 64: forward, PPO's clipped loss plus
the value loss, backward, and one Adam step, on CPU. Prints sample-gradients/s per thread count.

    python3 scripts/pytorch_reference.py --seconds 4 --threads 1 2
"""
import argparse
import time

import torch
import torch.nn as nn


def tower(out):
    return nn.Sequential(
        nn.Conv2d(1, 32, 8, 4), nn.ReLU(),
        nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
        nn.Conv2d(64, 64, 3, 1), nn.ReLU(),
        nn.Flatten(), nn.Linear(64 * 11 * 16, 512), nn.ReLU(),
        nn.Linear(512, out),
    )


def measure(threads, seconds, batch, adam):
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    pi, v = tower(10), tower(1)
    params = list(pi.parameters()) + list(v.parameters())
    opt = torch.optim.Adam(params, lr=3e-4)
    obs = torch.rand(batch, 1, 120, 160) * 255.0
    act = torch.randint(0, 10, (batch,))
    old_logp = torch.full((batch,), -2.3)
    adv = torch.randn(batch)
    ret = torch.randn(batch)

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
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        step()
        n += 1
    return n * batch / (time.perf_counter() - t0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--batch", type=int, default=64)
    a = ap.parse_args()
    print(f"torch {torch.__version__}, SHALLOW, both towers, minibatch {a.batch}")
    for t in a.threads:
        with_adam = measure(t, a.seconds, a.batch, True)
        without = measure(t, a.seconds, a.batch, False)
        print(f"{t} thread(s): forward + backward + Adam {with_adam:.0f} sample-gradients/s; "
              f"without Adam {without:.0f}")


if __name__ == "__main__":
    main()
