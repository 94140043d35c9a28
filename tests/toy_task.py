"""A tiny regression task for testing the training loop (also run under torchrun by a test)."""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch.utils.data import TensorDataset


class ToyTask:
    """y = x @ W_true + 0.5: a linear model learns it; validation reports the mean abs error."""

    kind = "toy"

    def __init__(self, n: int = 256, seed: int = 0, noise: float = 0.01):
        self.noise = noise
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(n, 8, generator=g)
        self.W = torch.randn(8, 3, generator=g)
        self.y = self.x @ self.W + 0.5

    def build_model(self, load_pretrained: bool = True) -> torch.nn.Module:
        torch.manual_seed(123)
        return torch.nn.Sequential(torch.nn.Linear(8, 32), torch.nn.ReLU(), torch.nn.Linear(32, 3))

    def train_dataset(self):
        return TensorDataset(self.x, self.y)

    def collate(self, items):
        return torch.stack([a for a, _ in items]), torch.stack([b for _, b in items])

    def compute_losses(self, model, batch, step, device):
        x, y = (t.to(device) for t in batch)
        noise = self.noise * torch.randn_like(y)  # uses the global RNG like augmentation does
        l1 = (model(x) - (y + noise)).abs().mean()
        return {"total": l1, "l1": l1.detach()}

    def validate(self, model, device):
        with torch.no_grad():
            return {"mae": float((model(self.x.to(device)) - self.y.to(device)).abs().mean())}

    def checkpoint_meta(self):
        return {"n_out": 3}


def main(argv: list[str]) -> None:
    """``python -m torch.distributed.run --nproc_per_node 2 tests/toy_task.py OUT STEPS BATCH``."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from cosy_lite.train.loop import LoopConfig, train
    from cosy_lite.train.schedule import OptimConfig

    out, steps, batch = argv[0], int(argv[1]), int(argv[2])
    loop = LoopConfig(steps=steps, batch_size=batch, num_workers=0, log_every=5, val_every=0, checkpoint_every=5, device="cpu")
    optim = OptimConfig(lr=3e-2, warmup_steps=5)
    train(ToyTask(noise=0.0), loop, optim, out, config={"loop": vars(loop), "optim": vars(optim)}, progress=False)


if __name__ == "__main__":
    main(sys.argv[1:])
