"""The `align` stage: backward alignment of a camera agent type into the LiDAR zoo's feature space (HEAL,
Lu et al., ICLR 2024, Sec. 4.2; models.aligner).

    v2vsim train --data CAMERA_DATA --stage align --encoder sinbevt --out ZOO --work WORK [--resume] [--bf16]

The base is the LiDAR zoo at --out (pointpillars_<preset>: its encoder, wire compressor and the fusion + heads
of the methods in AlignSpec.through), frozen. What trains is the new type's camera encoder (started from the
camera zoo's `single` encoder at --out where there is one, else from its ImageNet image backbone) and an
Aligner onto the base grid, from single-agent supervision only: one camera CAV's own frame, the vehicles its
own cameras saw. The loss is the base's perception loss through each frozen method of `through` on the aligned
map sent over the zoo's wire (as a neighbour's message reaches a LiDAR ego), plus, with distill_weight > 0,
the mean square distance of the aligned map to the frozen LiDAR encoder's map of the same CAV at the same
frame (the datasets record both sensors), relative to the latter's mean square.

The checkpoint is an add-on of the LiDAR zoo entry, `<base>/align_<encoder>.pt`, listed under the entry's
"aligned": {encoder: file}, its manifest record naming the sha256 of every base file it was trained against
(v2vsim.perception.aligned.build_aligned_encoder refuses a pairing with any other base)."""

from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from models import zoo
from models.aligner import AlignedEncoder, build_aligned_encoder
from models.build import build_cooperative, build_encoder, preset_image_backbone
from models.heads import AnchorTargetAssigner
from models.registry import MODALITY
from v2vsim.data.layout import DatasetError, runs_of
from v2vsim.data.torch_dataset import CooperativeDataset, collate
from v2vsim.training.loop import CHECKPOINT_EVERY_S, Checkpoint, Progress, one_cycle
from v2vsim.training.losses import perception_loss
from v2vsim.training.prepare import check_dataset_has_cameras
from v2vsim.training.stages import TrainArgs, _prefixed, wire_compressor
from v2vsim.training.validate import evaluate_samples

ALIGN = "align"
BASE_ENCODER = "pointpillars"


@dataclass(frozen=True)
class AlignSpec:
    """What the `align` stage trains and with which defaults (--epochs, --samples-per-epoch, --batch, --lr
    override them like any stage's)."""

    epochs: int = 3
    samples_per_epoch: int = 1400
    batch: int = 4
    lr: float = 2e-3
    blocks: int = 2  # the Aligner's residual blocks
    through: tuple[str, ...] = ("none", "cobevt")  # frozen base methods whose fusion + heads the loss goes through
    distill_weight: float = 1.0  # feature distillation from the LiDAR encoder on the same frame (0: off)
    # distillation weight of the cells of vehicles the camera saw, over 1 for the background; cells of vehicles it
    # did not see weigh 0 (a camera cannot know them: pulled towards LiDAR there it would learn to hallucinate)
    distill_focus: float = 0.0
    lane_weight: float = 3.0  # as every fine-tuning stage of the base
    val_samples: int = 120
    pretrained_lr_scale: float = 0.1  # the camera encoder (already trained) fine-tunes at this x lr


def aligned_file_name(encoder: str) -> str:
    return f"align_{encoder}.pt"


def _base_zoo(args: TrainArgs) -> zoo.Zoo:
    base = zoo.find(BASE_ENCODER, args.preset, args.out)
    if base is None or base.encoder_file is None:
        raise DatasetError(f"{args.out / zoo.MANIFEST}: no {zoo.zoo_name(BASE_ENCODER, args.preset)} zoo to align to; "
                           "the align stage joins a camera type to a trained LiDAR base (make zoo)")
    return base


def _state(ckpt: zoo.Checkpoint) -> dict:
    try:
        return ckpt.load()
    except zoo.ZooError as e:
        raise DatasetError(str(e)) from None


def base_files(base: zoo.Zoo, through: tuple[str, ...]) -> dict[str, str | None]:
    """{file: sha256} of the base checkpoints an aligned encoder is trained against: the encoder (its space),
    the wire's compressor and the methods it is aligned through."""
    files = [base.encoder_file, *([base.compressors[base.wire_ratio]] if base.wire_ratio > 1 else []),
             *(base.methods[m] for m in through)]
    return {c.path.name: c.sha256 for c in files if c is not None}


def _frozen(m: nn.Module) -> nn.Module:
    for p in m.parameters():
        p.requires_grad_(False)
    return m.eval()


def build_align_models(args: TrainArgs, spec: AlignSpec) -> tuple[AlignedEncoder, dict[str, nn.Module], nn.Module,
                                                                     dict]:
    """(the trainable aligned camera encoder, the frozen base method models of spec.through, the frozen LiDAR
    encoder, the start of the camera encoder {"file", "sha256"} or {} from ImageNet)."""
    base = _base_zoo(args)
    cells = base.cells
    methods = {}
    for m in spec.through:
        if m not in base.methods:
            raise DatasetError(f"{args.out / zoo.MANIFEST}: the base zoo has no {m} checkpoint to align through")
        torch.manual_seed(args.seed)
        model = build_cooperative(BASE_ENCODER, m, args.preset, cells=cells)
        state = _state(base.methods[m])
        model.fusion.load_state_dict(_prefixed(state, "fusion."))
        model.heads.load_state_dict(_prefixed(state, "heads."))
        methods[m] = _frozen(model)
    lidar = build_encoder(BASE_ENCODER, args.preset, cells=cells)
    lidar.load_state_dict(_prefixed(_state(base.encoder_file), "encoder."))  # type: ignore[arg-type]  # _base_zoo: not None
    cam = zoo.find(args.encoder, args.preset, args.out)
    backbone = (args.image_backbone or (None if cam is None else cam.image_backbone)
                or preset_image_backbone(args.encoder, args.preset))
    torch.manual_seed(args.seed)
    camera = build_encoder(args.encoder, args.preset, image_backbone=backbone)
    start: dict = {}
    if cam is not None and cam.encoder_file is not None and cam.image_backbone == backbone:
        path = cam.encoder_file.path
        camera.load_state_dict(_prefixed(_state(cam.encoder_file), "encoder."))
        start = {"file": f"{path.parent.name}/{path.name}", "sha256": cam.encoder_file.sha256}
    elif camera.image_backbone.pretrained:
        camera.image_backbone.load_pretrained()
    channels = lidar.out_channels
    return build_aligned_encoder(camera, channels, cells, spec.blocks), methods, _frozen(lidar), start


def _param_groups(aligned: AlignedEncoder, spec: AlignSpec, started: bool) -> list[dict]:
    """The camera encoder at spec.pretrained_lr_scale x lr when it starts trained (or its ImageNet backbone
    alone when it does not), the rest at lr."""
    slow = aligned.camera if started else aligned.image_backbone
    mine = {id(p) for p in slow.parameters()}
    params = list(aligned.parameters())
    return [{"params": [p for p in params if id(p) in mine], "lr": spec.lr * spec.pretrained_lr_scale},
            {"params": [p for p in params if id(p) not in mine], "lr": spec.lr}]


def _camera_inputs(batch: dict, dev: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """The batch's (only) agent's images in [0, 1] [B, M, 3, h, w], intrinsics, extrinsics."""
    return (batch["images"][:, 0].to(dev).float().div(255.0), batch["intrinsics"][:, 0].to(dev),
            batch["extrinsics"][:, 0].to(dev))


def align_losses(aligned: AlignedEncoder, methods: dict[str, nn.Module], lidar: nn.Module, wire: nn.Module | None,
                 batch: dict, spec: AlignSpec, assigner: AnchorTargetAssigner | None, dev: torch.device
                 ) -> dict[str, Tensor]:
    """The stage's losses on a batch of single-agent samples (see the module docstring)."""
    feats = aligned(*_camera_inputs(batch, dev))  # [B, C, F, F]
    sent = feats if wire is None else wire.over_the_wire(feats)
    rel = torch.zeros(len(feats), 1, 3, device=dev)
    valid = torch.ones(len(feats), 1, dtype=torch.bool, device=dev)
    losses: dict[str, Tensor] = {}
    for m, model in methods.items():
        fused = model.fuse(sent[:, None], rel, valid)
        out = {k: v.float() for k, v in model.heads(fused).items()}
        losses[m] = perception_loss(out, batch, "self", assigner, spec.lane_weight)["total"]
    total = sum(losses.values()) / len(losses)
    if spec.distill_weight > 0:
        with torch.no_grad():
            target = lidar([p[0].to(dev) for p in batch["points"]]).float()
            weight = distill_weights(batch, spec.distill_focus, feats.shape[-1], dev)  # [B, 1, F, F]
        err = (weight * (feats.float() - target).pow(2)).sum() / (weight.sum() * feats.shape[1]).clamp(min=1.0)
        losses["distill"] = spec.distill_weight * err / target.pow(2).mean().clamp(min=1e-6)
        total = total + losses["distill"]
    losses["total"] = total
    return losses


def distill_weights(batch: dict, focus: float, cells: int, dev: torch.device) -> Tensor:
    """[B, 1, F, F] per-cell distillation weights: 1 everywhere (focus 0), or 1 + focus on the cells of vehicles the
    agent's own sensors saw and 0 on those of vehicles it did not see (the masks max-pooled onto the feature grid)."""
    b = len(batch["valid"])
    if focus <= 0:
        return torch.ones(b, 1, cells, cells, device=dev)
    pool = torch.nn.functional.adaptive_max_pool2d
    seen = pool(batch["visible_self"][:, None].float(), cells).to(dev)
    unseen = pool((batch["dynamic"] & ~batch["visible_self"])[:, None].float(), cells).to(dev) * (1 - seen)
    return (1.0 + focus * seen) * (1.0 - unseen)


def validate_aligned(aligned: AlignedEncoder, methods: dict[str, nn.Module], ds: CooperativeDataset, n: int
                     ) -> dict[str, dict]:
    """Single-agent scores of the aligned camera map through each frozen base method (the ego's own scoring;
    v2vsim.training.validate.evaluate_samples), on the CPU; the models go back to their device."""
    dev = next(aligned.parameters()).device
    aligned.cpu().eval()
    try:
        models = {}
        for m, model in methods.items():
            model.cpu()
            model.encoder = aligned
            models[m] = model
        idx = np.linspace(0, len(ds) - 1, min(n, len(ds))).round().astype(int)
        return evaluate_samples(models, models["none" if "none" in models else next(iter(models))], ds,
                                [int(i) for i in idx])
    finally:
        for model in methods.values():
            model.to(dev)
        aligned.to(dev)


def run_align(args: TrainArgs, log=sys.stderr) -> dict:
    """Train (or resume) the align stage and export its checkpoint into the base zoo; returns the validation."""
    if MODALITY[args.encoder] != "camera":
        raise ValueError(f"--stage align aligns a camera encoder to the {BASE_ENCODER} zoo; got --encoder "
                         f"{args.encoder}")
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    check_dataset_has_cameras(args)
    spec = dataclasses.replace(AlignSpec(), **{k: v for k, v in args.overrides if hasattr(AlignSpec, k)})
    aligned, methods, lidar, start = build_align_models(args, spec)
    base = _base_zoo(args)
    wire = wire_compressor(dataclasses.replace(args, encoder=BASE_ENCODER))
    aligned, lidar = aligned.to(dev), lidar.to(dev)
    for m in methods.values():
        m.to(dev)
    if wire is not None:
        wire = wire.to(dev)
    train = CooperativeDataset(args.data, "train", max_agents=1, seed=args.seed, with_points=spec.distill_weight > 0,
                               with_images=True)
    val = CooperativeDataset(args.data, "val", max_agents=1, egos="first", with_points=False, with_images=True,
                             stride=2, seed=args.seed)
    groups = _param_groups(aligned, spec, bool(start))
    params = [p for g in groups for p in g["params"]]
    opt, sched, steps_per_epoch, total = one_cycle(groups, spec.lr, spec.epochs, spec.samples_per_epoch, spec.batch)
    assigner = AnchorTargetAssigner(next(iter(methods.values())).anchors)
    ckpt = Checkpoint(args.work / f"{ALIGN}_{args.encoder}", ALIGN)
    epoch, step, wall, history = ckpt.resume(aligned, opt, sched, args.resume, log)
    trained = sum(p.numel() for p in aligned.parameters())
    frozen = sum(p.numel() for m in methods.values() for p in [*m.fusion.parameters(), *m.heads.parameters()])
    print(f"[{ALIGN}] {args.encoder} -> {zoo.zoo_name(BASE_ENCODER, args.preset)}: training {trained:,} parameters "
          f"(camera encoder {'from ' + start['file'] if start else 'from ImageNet'} + aligner), frozen base "
          f"{frozen:,} ({', '.join(spec.through)}), distill weight {spec.distill_weight}", file=log, flush=True)

    def save(ep: int, st: int) -> None:
        ckpt.save(aligned, opt, sched, ep, st, wall + time.monotonic() - t_seg, history, dataclasses.asdict(spec))

    t_seg = time.monotonic()
    last_save = t_seg
    prog = Progress(ALIGN, total, epoch * steps_per_epoch + step, log)
    samples = 0
    while epoch < spec.epochs:
        aligned.train()
        perm = np.resize(np.random.default_rng([args.seed, epoch]).permutation(len(train)),
                         steps_per_epoch * spec.batch)
        running: dict[str, float] = {}
        for s in range(step, steps_per_epoch):
            batch = collate([train[int(j)] for j in perm[s * spec.batch:(s + 1) * spec.batch]])
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=args.bf16):
                losses = align_losses(aligned, methods, lidar, wire, batch, spec, assigner, dev)
            opt.zero_grad(set_to_none=True)
            losses["total"].float().backward()
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
        metrics = validate_aligned(aligned, methods, val, spec.val_samples)
        history.append({"epoch": epoch + 1, "loss": running, "validation": metrics})
        print(f"[{ALIGN}] epoch {epoch + 1}/{spec.epochs} validation (one camera CAV, aligned, through the base): "
              + ", ".join(f"{m}: IoU veh {v['iou_vehicle']} road {v['iou_road']} lane {v['iou_lane']} AP50 {v['ap50']}"
                          for m, v in metrics.items()), file=log, flush=True)
        epoch, step = epoch + 1, 0
        save(epoch, 0)
        last_save = time.monotonic()
    wall_total = wall + time.monotonic() - t_seg
    path = args.out / zoo.zoo_name(BASE_ENCODER, args.preset) / aligned_file_name(args.encoder)
    cam = zoo.find(args.encoder, args.preset, args.out)
    state = {f"encoder.{k}": v for k, v in aligned.state_dict().items()}
    zoo.save_checkpoint(path, state, encoder=args.encoder, preset=args.preset, stage=ALIGN, methods=[],
                        config={"spec": dataclasses.asdict(spec), "seed": args.seed, "bf16": args.bf16})
    manifest = train.store.manifest
    runs = {s: [r["name"] for r in runs_of(manifest, s)] for s in ("train", "val", "eval")}
    info = {
        "stage": ALIGN,
        "command": args.command or f"v2vsim train --data {args.data} --stage align --encoder {args.encoder} "
                                   f"--out {args.out}",
        "data": {"root": str(args.data), "runs": runs,
                 "train_frames": sum(r["frames"] for r in runs_of(manifest, "train"))},
        "epochs": spec.epochs, "samples_per_epoch": spec.samples_per_epoch, "batch": spec.batch,
        "wall_s": round(wall_total, 1), "device": args.device, "threads": args.threads, "bf16": args.bf16,
        "validation": history[-1]["validation"] if history else None,
        "aligns": {"encoder": args.encoder, "image_backbone": (None if cam is None else cam.image_backbone)
                   or args.image_backbone or preset_image_backbone(args.encoder, args.preset),
                   "blocks": spec.blocks, "through": list(spec.through), "distill_weight": spec.distill_weight,
                   "distill_focus": spec.distill_focus,
                   "base": base_files(base, spec.through), "start": start,
                   "trained_parameters": trained, "frozen_base_parameters": frozen},
    }
    zoo.register(path, encoder=BASE_ENCODER, preset=args.preset, methods=[], info=info, root=args.out,
                 aligns=args.encoder)
    print(f"[{ALIGN}] done: {path} ({wall_total / 60:.1f} min)", file=log, flush=True)
    return history[-1]["validation"] if history else {}
