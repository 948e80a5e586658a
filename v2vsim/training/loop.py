"""What every training loop shares (the stages of v2vsim.training.train and the align stage of
v2vsim.training.align): AdamW with a one-cycle schedule, the resumable checkpoint under --work, and the progress
line with loss, samples/s and ETA."""

from __future__ import annotations

import time
from pathlib import Path

import torch
from torch import nn

CHECKPOINT_EVERY_S = 300.0


def one_cycle(groups: list[dict], lr: float, epochs: int, samples_per_epoch: int, batch: int
              ) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.OneCycleLR, int, int]:
    """(AdamW over the parameter groups, each at its own peak rate, its one-cycle schedule, steps per epoch,
    steps in all)."""
    opt = torch.optim.AdamW(groups, lr=lr, weight_decay=1e-2)
    steps_per_epoch = max(1, samples_per_epoch // batch)
    total = steps_per_epoch * epochs
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=[g["lr"] for g in groups], total_steps=total,
                                                pct_start=0.1)
    return opt, sched, steps_per_epoch, total


class Checkpoint:
    """A stage's `last.pt` in its work folder: the model, optimiser and schedule, where the stage stopped (epoch,
    step), the wall time so far and the validation history; written atomically (a kill mid-write loses nothing)."""

    def __init__(self, work: Path, name: str) -> None:
        work.mkdir(parents=True, exist_ok=True)
        self.path = work / "last.pt"
        self.name = name

    def resume(self, model: nn.Module, opt: torch.optim.Optimizer, sched: object, resume: bool, log
               ) -> tuple[int, int, float, list]:
        """Load it into model, opt and sched when `resume` and it exists: (epoch, step, wall_s, history); else
        the start, (0, 0, 0.0, []). Says which on `log`."""
        if resume and self.path.is_file():
            ck = torch.load(self.path, map_location="cpu", weights_only=False)
            model.load_state_dict(ck["model"])
            opt.load_state_dict(ck["opt"])
            sched.load_state_dict(ck["sched"])  # type: ignore[attr-defined]
            print(f"[{self.name}] resuming at epoch {ck['epoch'] + 1}, step {ck['step']}", file=log, flush=True)
            return ck["epoch"], ck["step"], ck["wall_s"], ck["history"]
        if self.path.is_file():
            print(f"[{self.name}] starting over ({self.path} exists; --resume continues it)", file=log)
        elif resume:
            print(f"[{self.name}] --resume: nothing to resume ({self.path} does not exist): starting from scratch",
                  file=log)
        return 0, 0, 0.0, []

    def save(self, model: nn.Module, opt: torch.optim.Optimizer, sched: object, epoch: int, step: int,
             wall_s: float, history: list, spec: dict) -> None:
        tmp = self.path.with_suffix(".tmp")
        torch.save({"model": model.state_dict(), "opt": opt.state_dict(),
                    "sched": sched.state_dict(),  # type: ignore[attr-defined]
                    "epoch": epoch, "step": step, "wall_s": wall_s, "history": history, "spec": spec}, tmp)
        tmp.replace(self.path)


class Progress:
    """The progress line, at most every 10 s: epoch, step, the running losses, samples/s, ETA."""

    def __init__(self, stage: str, total: int, done: int, log) -> None:
        self.stage, self.total, self.start_done, self.log = stage, total, done, log
        self.t0 = time.monotonic()
        self.last = 0.0

    def show(self, done: int, samples: int, epoch: int, epochs: int, losses: dict[str, float], force: bool = False
             ) -> None:
        now = time.monotonic()
        if not force and now - self.last < 10.0:
            return
        self.last = now
        rate = samples / max(now - self.t0, 1e-9)
        left = (self.total - done) * (samples / max(done - self.start_done, 1)) / max(rate, 1e-9)
        parts = " ".join(f"{k} {v:.4g}" for k, v in losses.items())
        print(f"[{self.stage}] epoch {epoch + 1}/{epochs} step {done}/{self.total}  loss {parts}  "
              f"{rate:.1f} samples/s  ETA {left / 60:.1f} min", file=self.log, flush=True)
