"""Training stages of a model zoo (CoBEVT authors' recipe: single-agent model first, then fusion
on the frozen encoder so that every method fuses the very same wire message). LiDAR (pointpillars) or
camera (sinbevt, lara: `--encoder`); a camera zoo has no `early` stage (early fusion ships LiDAR points),
and its DiscoNet trains without distillation (its teacher is early fusion).

    single   encoder + decoder/heads on one CAV's own sweep (this is `none`, and `late` per CAV);
             targets: the vehicles the CAV's own sensors saw (others are ignored, not negatives)
    cache    the frozen single-agent encoder's features of every CAV frame, float16 (the wire payload)
    early    encoder + heads (from `single`) on clouds merged in the ego frame (OPV2V early fusion)
    attfuse / fcooper / v2vnet / cobevt, and a fusion plugin's stage (its name; not part of `all`)
             fusion module + heads (heads from `single`) on the cached features of the ego and the
             CAVs within range, neighbours randomly 0-1 frames old (a 27 Mbps link delivers one frame late)
    disconet as above, plus DiscoNet's distillation: its fused map is pulled towards the early-fusion
             teacher's features (KL over channels per cell; Li et al. 2021, Eq. 6)
    extrapolate  (on its own, not in `all`) receiver-side latency compensation (models.extrapolation,
             FFNet-style first-order extrapolation) for the zoo's CoBEVT (--out; fusion + heads frozen) on the
             same cache: neighbours 1-5 frames late, each with the message before it

Losses (models.losses): focal loss on the dynamic class, cross-entropy on road/lane, focal +
smooth-L1 on the anchor head. AdamW with a one-cycle schedule; seeded; progress with loss,
samples/s and ETA; validation (the one prediction path, v2vsim.evaluation.fuse_and_score) after every epoch;
checkpoints every few minutes and per epoch under --work; `--resume` continues mid-epoch.
"""

from __future__ import annotations

import dataclasses
import shlex
import sys
import time

import numpy as np
import torch
from torch import Tensor, nn

from models.compression import ChannelCompressor
from models.heads import AnchorTargetAssigner
from models.registry import MODALITY
from v2vsim.data.torch_dataset import CooperativeDataset, collate, open_store, tensor_inputs
from v2vsim.training.align import ALIGN, run_align
from v2vsim.training.augment import yaw_rotate_batch
from v2vsim.training.cache import (
    FeatureCache,
    build_feature_cache,
    write_cache_encoder,
)
from v2vsim.training.export import export
from v2vsim.training.extrapolate import extrapolate_batch
from v2vsim.training.held_out import check_held_out, is_v2vsim_dataset
from v2vsim.training.loop import CHECKPOINT_EVERY_S, Checkpoint, Progress, one_cycle
from v2vsim.training.losses import distill_loss, perception_loss
from v2vsim.training.prepare import (
    cache_encoder,
    check_cache_encoder,
    check_cache_grid,
    check_dataset_has_cameras,
    on_wire,
)
from v2vsim.training.stages import (
    COMPRESS,
    EXTRAPOLATE,
    SPECS,
    StageSpec,
    TrainArgs,
    _prefixed,
    build_stage_model,
    build_training_model,
    check_zoo_grid,
    load_stage_state,
    param_groups,
    stage_dir,
    stage_file,
    stage_spec,
    stages_for,
    state_to_save,
    wire_compressor,
)
from v2vsim.training.validate import validate

CACHE_STRIDE = 1


# ---- the loop ------------------------------------------------------------------------------------


def _features(cache: FeatureCache, batch: dict, channels: int, cells: int) -> Tensor:
    """[B, L, C, F, F] float32 from the cache (each agent at the frame its message was captured)."""
    b, lmax = batch["valid"].shape
    out = torch.zeros(b, lmax, channels, cells, cells)
    for i, (key, agents, frames) in enumerate(zip(batch["key"], batch["agents"], batch["agent_frames"], strict=True)):
        for j, (c, k) in enumerate(zip(agents, frames, strict=True)):
            out[i, j] = torch.from_numpy(cache.get(key.run, k, c).astype(np.float32))
    return out


def forward(model: nn.Module, spec: StageSpec, batch: dict, cache: FeatureCache | None, dev: torch.device,
            wire: ChannelCompressor | None = None) -> dict[str, Tensor]:
    """The stage's outputs on a batch; the neighbours' cached features pass through the frozen `wire` compressor
    (the zoo's wire ratio) as the ego receives them (its own map is its own: never compressed), or for the
    `compress` stage one CAV's map through the compressor it trains."""
    rel, valid = batch["rel_poses"].to(dev), batch["valid"].to(dev)
    if spec.inputs == "cache":
        enc = model.encoder
        feats = _features(cache, batch, enc.out_channels, enc.out_cells).to(dev)
        if spec.name == COMPRESS:
            decoded = model.compressor.over_the_wire(feats[:, 0])  # one CAV's own map
            out = model.heads(decoded)
            ms = feats[:, 0].pow(2).mean().clamp(min=1e-6)
            return {"fused": decoded, **out, "recon": (decoded - feats[:, 0]).pow(2).mean() / ms}
        if wire is not None:  # the neighbours' maps came over the air; the ego's own (slot 0) did not
            with torch.no_grad():
                feats = torch.cat([feats[:, :1], wire.over_the_wire(feats[:, 1:])], dim=1)
        if spec.name == EXTRAPOLATE:
            feats = extrapolate_batch(model.extrapolation, feats, batch, cache, model.bev_size_m, wire)
        fused = model.fuse(feats, rel, valid)
        return {"fused": fused, **model.heads(fused)}
    return model(*tensor_inputs(batch, dev))


def run_stage(args: TrainArgs, log=sys.stderr) -> dict:
    """Train (or resume) one stage and export its checkpoint into the zoo; returns the validation metrics."""
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    camera = MODALITY[args.encoder] == "camera"
    if camera and args.stage == "early":
        raise ValueError(f"--stage early: early fusion ships LiDAR points; the {args.encoder} (camera) zoo has no "
                         "early stage")
    check_zoo_grid(args)
    if camera:
        check_dataset_has_cameras(args)
    if args.stage == "cache":
        encoder, source = cache_encoder(args, log)
        store = open_store(args.data)  # the cache needs sensor data only (an OPV2V folder may lack BEV maps)
        build_feature_cache(encoder.to(dev), store, ("train", "val"), args.work / "cache",
                            stride=CACHE_STRIDE, log=log, camera=camera)
        write_cache_encoder(args.work / "cache", source, encoder.state_dict())
        return {}
    spec = dataclasses.replace(stage_spec(args.stage), **dict(args.overrides))
    if spec.name == COMPRESS:
        if camera or len(args.ratios) != 1:
            raise ValueError(f"--stage compress: one ratio per run of the stage (main_train loops over --ratios), "
                             f"for a LiDAR zoo; got {args.ratios} for {args.encoder}")
        spec = dataclasses.replace(spec, ratio=args.ratios[0])
    if args.wire_ratio is not None:
        spec = on_wire(args, spec)
    if spec.name == EXTRAPOLATE:
        check_cache_encoder(args, spec, log)
    if camera and spec.distill_weight > 0:  # DiscoNet's teacher is early fusion: LiDAR only
        spec = dataclasses.replace(spec, distill_weight=0.0)
    if spec.yaw_jitter_deg and not (camera and spec.inputs == "points" and spec.max_agents == 1):
        raise ValueError(f"--yaw-jitter: turns one camera agent's frame; stage {spec.name!r} of {args.encoder} "
                         "cannot use it (only a camera zoo's `single` stage)")
    cache = FeatureCache(args.work / "cache") if spec.inputs == "cache" else None
    if cache is not None:
        check_cache_grid(cache, args)
    # the neighbours' maps come through the zoo's wire compressor (a stage without neighbours, `none`, reads none)
    wire = wire_compressor(args) if spec.inputs == "cache" and spec.name != COMPRESS and spec.max_agents > 1 else None
    if wire is not None:
        print(f"[{spec.name}] features through the zoo's wire compressor, ratio {wire.ratio}", file=log, flush=True)
    elif spec.wire_ratio == 1:
        print(f"[{spec.name}] features uncompressed (--wire-ratio 1)", file=log, flush=True)
    raw = spec.inputs == "points" or spec.distill_weight > 0  # the encoder (or the teacher) runs on sensor data
    extrapolate = spec.name == EXTRAPOLATE
    train = CooperativeDataset(args.data, "train", max_agents=spec.max_agents, delays=spec.delays, seed=args.seed,
                               with_points=raw and not camera, with_images=raw and camera, stride=spec.stride,
                               with_previous=extrapolate)
    # (the extrapolate stage validates on late neighbours: its training delays, drawn alike every epoch)
    val = CooperativeDataset(args.data, "val", max_agents=5 if "late" in spec.methods or not spec.methods
                             else spec.max_agents,
                             egos="first", with_points=cache is None and not camera,
                             with_images=cache is None and camera, stride=2,
                             delays=spec.delays if extrapolate else (0,), seed=args.seed, with_previous=extrapolate)
    model = build_stage_model(args, spec).to(dev)
    # the single-agent model: its encoder makes the wire features; with its heads, CAVs' late outputs
    # (the extrapolate stage reads every feature from the cache and scores no late method: it needs none)
    single = model if spec.name in ("single", "none", EXTRAPOLATE, COMPRESS) else build_stage_model(args, SPECS["none"])
    teacher = None
    if spec.distill_weight > 0:
        teacher = build_training_model(args, "early")
        st = load_stage_state(args, "early")
        teacher.encoder.load_state_dict(_prefixed(st, "encoder."))
        teacher.heads.load_state_dict(_prefixed(st, "heads."))
        teacher = teacher.to(dev).eval()
    groups = param_groups(model, spec)
    params = [p for g in groups for p in g["params"]]
    opt, sched, steps_per_epoch, total = one_cycle(groups, spec.lr, spec.epochs, spec.samples_per_epoch, spec.batch)
    assigner = AnchorTargetAssigner(model.anchors) if model.heads.detection is not None else None
    ckpt = Checkpoint(stage_file(args, stage_dir(spec)).parent, spec.name)
    epoch, step, wall, history = ckpt.resume(model, opt, sched, args.resume, log)

    def save(ep: int, st: int) -> None:
        ckpt.save(model, opt, sched, ep, st, wall + time.monotonic() - t_seg, history, dataclasses.asdict(spec))

    t_seg = time.monotonic()
    last_save = t_seg
    prog = Progress(spec.name, total, epoch * steps_per_epoch + step, log)
    samples = 0
    while epoch < spec.epochs:
        model.train()
        if spec.inputs == "cache":
            model.encoder.eval()
        if extrapolate or spec.name == COMPRESS:  # the model stays in inference mode (frozen); the add-on trains
            model.eval()
            (model.extrapolation if extrapolate else model.compressor).train()
        train.epoch = epoch
        perm = np.random.default_rng([args.seed, epoch]).permutation(len(train))
        perm = np.resize(perm, steps_per_epoch * spec.batch)
        running: dict[str, float] = {}
        for s, batch in enumerate(batches(train, perm, spec.batch, step, steps_per_epoch, args.workers), start=step):
            if spec.yaw_jitter_deg:  # seeded per step, so a resumed run draws the same angles
                u = torch.from_numpy(np.random.default_rng([args.seed, epoch, s]).uniform(-1, 1, len(batch["valid"])))
                batch = yaw_rotate_batch(batch, torch.deg2rad(u * spec.yaw_jitter_deg), model.bev_size_m)
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=args.bf16):
                out = forward(model, spec, batch, cache, dev, wire)
            out = {k: v.float() for k, v in out.items()}
            losses = perception_loss(out, batch, spec.target, assigner, spec.lane_weight)
            if spec.recon_weight:
                losses["recon"] = spec.recon_weight * out["recon"]
                losses["total"] = losses["total"] + losses["recon"]
            if teacher is not None:
                with torch.no_grad():
                    t_out = teacher(*tensor_inputs(batch, dev))
                losses["kd"] = spec.distill_weight * distill_loss(out["fused"], t_out["fused"])
                losses["total"] = losses["total"] + losses["kd"]
            opt.zero_grad(set_to_none=True)
            if losses["total"].requires_grad:  # (extrapolate: a batch without a late message trains nothing)
                losses["total"].backward()
                torch.nn.utils.clip_grad_norm_(params, 10.0)
                opt.step()
            sched.step()
            samples += spec.batch
            for k, v in losses.items():
                running[k] = 0.9 * running.get(k, float(v.detach())) + 0.1 * float(v.detach())
            prog.show(epoch * steps_per_epoch + s + 1, samples, epoch, spec.epochs, running)
            if time.monotonic() - last_save > CHECKPOINT_EVERY_S:
                save(epoch, s + 1)
                last_save = time.monotonic()
        if (epoch + 1) % max(args.val_every, 1) == 0 or epoch + 1 == spec.epochs:
            metrics = validate(spec, model, single, val, cache, spec.val_samples, wire)
            history.append({"epoch": epoch + 1, "loss": running, "validation": metrics})
            summary = ", ".join(f"{m}: IoU veh {v['iou_vehicle']} road {v['iou_road']} lane {v['iou_lane']} "
                                f"AP50 {v['ap50']} AP70 {v['ap70']}" for m, v in metrics.items())
            print(f"[{spec.name}] epoch {epoch + 1}/{spec.epochs} validation: {summary}", file=log, flush=True)
            if extrapolate:
                (m,) = spec.methods
                without, with_ = metrics[m]["iou_vehicle"], metrics[f"{m}_extrapolated"]["iou_vehicle"]
                print(f"[{spec.name}] {m} vehicle IoU, neighbours {min(spec.delays)}-{max(spec.delays)} frames late: "
                      f"{without} without extrapolation, {with_} with it", file=log, flush=True)
        else:
            history.append({"epoch": epoch + 1, "loss": running, "validation": None})
        epoch, step = epoch + 1, 0
        save(epoch, 0)
        last_save = time.monotonic()
    wall_total = wall + time.monotonic() - t_seg
    final = state_to_save(model, spec)
    final_path = stage_file(args, stage_dir(spec))
    torch.save({"state_dict": final, "spec": dataclasses.asdict(spec)}, final_path)
    export(args, spec, final, history, wall_total, train.store.manifest)
    return history[-1]["validation"] if history else {}


def batches(ds: CooperativeDataset, perm: np.ndarray, batch: int, first: int, steps: int, workers: int):
    """The collated batches `first`..`steps`-1 of an epoch's permutation, loaded in `workers` processes
    (0: here). Workers copy `ds` when the epoch starts, so they see its current `epoch` (delay draws)."""
    chunks = [[int(j) for j in perm[s * batch:(s + 1) * batch]] for s in range(first, steps)]
    if workers <= 0:
        return (collate([ds[j] for j in c]) for c in chunks)
    return iter(torch.utils.data.DataLoader(ds, batch_sampler=chunks, collate_fn=collate, num_workers=workers,
                                            prefetch_factor=4, persistent_workers=False))


def main_train(args: TrainArgs, log=sys.stderr) -> int:
    if is_v2vsim_dataset(args.data):  # the benchmark's networks never train (v2vsim/training/held_out.py)
        check_held_out(args.data)
    if args.stage == ALIGN:  # a camera type joins the LiDAR zoo at --out (v2vsim.training.align)
        t0 = time.monotonic()
        run_align(args, log=log)
        print(f"[{ALIGN}] done in {(time.monotonic() - t0) / 60:.1f} min", file=log, flush=True)
        return 0
    for st in stages_for(args.stage, args.encoder):
        for ratios in ([(r,) for r in args.ratios] if st == COMPRESS else [args.ratios]):
            t0 = time.monotonic()
            run_stage(dataclasses.replace(args, stage=st, ratios=ratios), log=log)
            what = f"{st} (ratio {ratios[0]})" if st == COMPRESS else st
            print(f"[{what}] done in {(time.monotonic() - t0) / 60:.1f} min", file=log, flush=True)
    return 0


def command_line(argv: list[str]) -> str:
    return "v2vsim train " + " ".join(shlex.quote(a) for a in argv)
