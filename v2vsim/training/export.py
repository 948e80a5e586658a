"""A trained stage into the zoo (models.zoo): its checkpoint file (single.pt, <method>.pt, <method>_r<R>.pt on
another wire, <method>_extrapolate.pt, compressor_r<R>.pt) and its manifest entry: how it was trained, on what
data, and its last validation."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from models import zoo
from v2vsim.data.layout import runs_of
from v2vsim.training.held_out import data_inputs_sha256
from v2vsim.training.stages import (
    COMPRESS,
    EXTRAPOLATE,
    WIRE_RATIO,
    StageSpec,
    TrainArgs,
    train_cells,
    train_image_backbone,
)


def export(args: TrainArgs, spec: StageSpec, state: dict, history: list, wall_s: float, manifest: dict) -> Path:
    """Write the stage's checkpoint into the zoo and its manifest entry (the extrapolate stage: an add-on
    file "<method>_extrapolate.pt" under the zoo entry's "extrapolation", beside the method's own file)."""
    extrapolate = spec.name == EXTRAPOLATE
    name = "single.pt" if spec.name == "single" else f"{spec.name}.pt"
    if extrapolate:
        name = f"{spec.methods[0]}_{EXTRAPOLATE}.pt"
    if spec.name == COMPRESS:
        name = f"compressor_r{spec.ratio}.pt"
    if spec.wire_ratio is not None:
        name = f"{spec.name}_r{spec.wire_ratio}.pt"
    path = args.out / zoo.zoo_name(args.encoder, args.preset) / name
    cells = train_cells(args)
    config = {"spec": dataclasses.asdict(spec), "seed": args.seed, "encoder": args.encoder, "preset": args.preset,
              "cells": cells, "bf16": args.bf16, "image_backbone": train_image_backbone(args)}
    zoo.save_checkpoint(path, state, encoder=args.encoder, preset=args.preset, stage=spec.name,
                        methods=list(spec.methods), config=config)
    runs = {s: [r["name"] for r in runs_of(manifest, s)] for s in ("train", "val", "eval")}
    info = {
        "stage": spec.name,
        "command": args.command or f"v2vsim train --data {args.data} --stage {spec.name} --out {args.out}",
        "data": {"root": str(args.data), "runs": runs,
                 "train_frames": sum(r["frames"] for r in runs_of(manifest, "train")),
                 "inputs_sha256": data_inputs_sha256(args.data)},
        "epochs": spec.epochs, "samples_per_epoch": spec.samples_per_epoch, "batch": spec.batch,
        "wall_s": round(wall_s, 1), "device": args.device, "threads": args.threads, "bf16": args.bf16,
        "validation": history[-1]["validation"] if history else None,
    }
    if spec.wire_ratio is not None:  # trained on another wire than the zoo's (Checkpoint.rebuild_command repeats it)
        info["wire_ratio"] = spec.wire_ratio
    if extrapolate:  # the checkpoint it was trained on top of (build_extrapolation refuses another one)
        base = zoo.find(args.encoder, args.preset, args.out).method(spec.methods[0])
        info["extrapolates"] = {"method": spec.methods[0], "file": base.path.name, "sha256": base.sha256}
    zoo.register(path, encoder=args.encoder, preset=args.preset, methods=[] if extrapolate else list(spec.methods),
                 info=info, root=args.out, provides_encoder=spec.name == "single",
                 extrapolates=tuple(spec.methods) if extrapolate else (), cells=cells,
                 compresses=spec.ratio if spec.name == COMPRESS else None, trained_wire=spec.wire_ratio,
                 image_backbone=train_image_backbone(args))
    if spec.name == COMPRESS and spec.ratio == WIRE_RATIO:  # every later stage trains on this wire
        zoo.set_wire_ratio(args.encoder, args.preset, WIRE_RATIO, args.out)
    return path
