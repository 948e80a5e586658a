"""What a training stage resolves and checks before its loop (v2vsim.training.train.run_stage): a camera zoo's
dataset has camera images; the encoder that fills the feature cache (the `single` stage's, or the zoo's); a cache
made at this training's grid and, for `extrapolate`, by the zoo's encoder; the wire an intermediate fusion stage
trains on (--wire-ratio)."""

from __future__ import annotations

import dataclasses
import json

from torch import nn

from models import zoo
from models.registry import intermediate_methods, is_intermediate
from v2vsim.data.layout import DatasetError
from v2vsim.data.torch_dataset import open_store
from v2vsim.training.cache import FeatureCache, encoder_fingerprint, read_cache_encoder
from v2vsim.training.stages import (
    EXTRAPOLATE,
    SPECS,
    StageSpec,
    TrainArgs,
    _prefixed,
    build_stage_model,
    build_training_model,
    load_stage_state,
    stage_file,
    train_cells,
    zoo_state,
)


def check_dataset_has_cameras(args: TrainArgs) -> None:
    """A camera encoder trains on a dataset recorded with cameras: DatasetError naming the first run without."""
    store = open_store(args.data)
    for r in store.manifest["runs"]:
        if store.runs[r["name"]].get("format") == "opv2v":
            if not store.runs[r["name"]]["cameras"]:
                raise DatasetError(f"{store.runs[r['name']]['source']}: OPV2V scenario without camera images "
                                   f"(<timestamp>_camera0..3.png); --encoder {args.encoder} trains on camera images")
            continue
        info = args.data / r["name"] / "run.json"
        if info.is_file() and not json.loads(info.read_text()).get("cameras", False):
            raise DatasetError(f"{info}: run {r['name']} was recorded without cameras; --encoder {args.encoder} "
                               "trains on camera images: record the dataset with `v2vsim dataset ... --cameras "
                               "--set perception.modality=camera` (scripts/camera_zoo.sh)")


def cache_encoder(args: TrainArgs, log) -> tuple[nn.Module, str]:
    """The encoder that fills the feature cache, and where its weights come from: the `single` stage's
    output under --work, or (when --work has none) the encoder of the zoo at --out, so that a cache can
    be made for an existing zoo (e.g. to train `extrapolate` on top of it)."""
    if stage_file(args, "single").is_file():
        return build_stage_model(args, SPECS["none"]).encoder, str(stage_file(args, "single"))
    z = zoo.find(args.encoder, args.preset, args.out)
    ckpt = None if z is None else z.encoder_file
    if ckpt is None:  # neither: the usual "train single first" error
        load_stage_state(args, "single")
    encoder = build_training_model(args, "none").encoder
    encoder.load_state_dict(_prefixed(zoo_state(args, "encoder"), "encoder."))
    print(f"[cache] {stage_file(args, 'single')} does not exist: encoding with the zoo's encoder {ckpt.path}",
          file=log, flush=True)
    return encoder, str(ckpt.path)


def check_cache_grid(cache: FeatureCache, args: TrainArgs) -> None:
    """A cache holds one grid's features: refuse one made at another grid than this training's."""
    cells = train_cells(args)
    if cells is not None and tuple(cache.shape[-2:]) != (cells, cells):
        raise DatasetError(f"{args.work / 'cache'}: features of a {cache.shape[-1]} x {cache.shape[-1]} grid, this "
                           f"training is at {cells} x {cells}; use another --work (or rebuild its cache)")


def check_cache_encoder(args: TrainArgs, spec: StageSpec, log) -> None:
    """The extrapolate stage's inputs: the method in the zoo (--out), and a feature cache under --work made by
    the encoder the zoo's methods were trained on."""
    zoo_state(args, spec.methods[0])
    if not (args.work / "cache" / "index.json").is_file():
        raise DatasetError(f"{args.work / 'cache'}: no feature cache; make it first: `v2vsim train --data {args.data} "
                           f"--stage cache --out {args.out} --work {args.work}`")
    cached = read_cache_encoder(args.work / "cache")
    if cached is None:
        print(f"[{EXTRAPOLATE}] {args.work / 'cache'} does not record its encoder (made before that was recorded): "
              "assuming it is the zoo's", file=log, flush=True)
        return
    mine = encoder_fingerprint(_prefixed(zoo_state(args, "encoder"), "encoder."))
    if cached["fingerprint"] != mine:
        raise ValueError(f"{args.work / 'cache'}: made by the encoder of {cached['source']}, not by the encoder of "
                         f"the zoo at {args.out} whose methods this stage extends; rebuild the cache for this zoo "
                         f"(`v2vsim train --stage cache --out {args.out}` with a --work without single/final.pt) "
                         "or use the zoo trained with this --work")


def on_wire(args: TrainArgs, spec: StageSpec) -> StageSpec:
    """--wire-ratio R: an intermediate fusion stage trained on the ratio-R wire (its compressor from the zoo; 1:
    uncompressed) into its own checkpoint <method>_r<R>.pt (manifest "wire_methods"), the one runs with
    comm.channel_compression: R load; on the zoo's own wire ratio it is the stage as usual."""
    if args.wire_ratio < 1 or spec.name == EXTRAPOLATE or spec.inputs != "cache" or len(spec.methods) != 1 \
            or not is_intermediate(spec.methods[0]):
        raise ValueError(f"--wire-ratio {args.wire_ratio}: trains an intermediate fusion method "
                         f"({', '.join(intermediate_methods())}) on another wire; stage {spec.name!r} fuses no "
                         "neighbours' features (the ratio must be >= 1)")
    z = zoo.find(args.encoder, args.preset, args.out)
    if args.wire_ratio == (1 if z is None else z.wire_ratio):
        return spec
    return dataclasses.replace(spec, wire_ratio=args.wire_ratio)
