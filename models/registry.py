"""Build models by name: encoders, fusion methods, heads, the composed cooperative model; ONE open registry of
the names.

Every encoder and fusion method is a `Registration` in this registry: the built-ins are registered below (lazily,
by "module:attribute", so that importing this module imports no torch and the scenario checks stay light);
code inside the package registers more with the `register_fusion` decorator; an installed distribution adds
fusion methods through Python entry points in group "v2vsim.fusion" (FUSION_GROUP):

    [project.entry-points."v2vsim.fusion"]
    maxfuse = "maxfuse:MaxFusion"

The entry points are read once, lazily (importlib.metadata), the first time the registry is asked for a name it
does not know, for the full list, or to check the methods a scenario requests (`check_methods`). A plugin's object
is imported the first time it is built or requested, and checked then against the fusion contract
(models.fusion.contract.check_fusion_module, models.fusion.base). Whatever goes wrong (it cannot be imported,
breaks the contract, its name is taken by a built-in or by another distribution, or is no method name) is a
PluginError naming the entry point, the object it points at and what it broke, raised whenever that name is
requested; `v2vsim models` lists it as broken with the reason.

A fusion method is a factory (an nn.Module class) called as ``factory(channels, **kwargs)``; a plugin's object
may carry two optional attributes: ``preset_kwargs`` ({preset name: {keyword: value}}, the sizes of each model
preset) and ``weights`` (a zoo folder shipped in its package, as `v2vsim train --out` writes it:
v2vsim.perception.build loads the method's checkpoint from there under `perception.weights: auto` when the
scenario's zoo has none, if it was trained on the very encoder and wire of that zoo).

"early" and "late" are brackets around the single-agent model, not fusion modules: they are methods (METHODS)
but not in FUSION. METHODS, FUSION, ENCODERS and MODALITY are live views over the registry (a list, and
mappings name -> factory / modality): iterating them sees every plugin.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from torch import nn

    from models.cooperative import CooperativePerception
    from models.heads import BevHeads

FUSION_GROUP = "v2vsim.fusion"
BUILTIN_METHODS = ("none", "late", "early", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt")
BRACKETS = ("late", "early")  # methods around the single-agent model, no fusion module of their own
# A plugin's name goes into --methods lists, YAML lists, checkpoint file names (NAME.pt) and --stage.
METHOD_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")
# Names taken elsewhere: `v2vsim train --stage` values that are no method, and the zoo's "encoder" pseudo-method.
RESERVED = ("all", "single", "cache", "compress", "extrapolate", "encoder")

BUILTIN, ENTRY_POINT, REGISTERED = "built-in", "entry point", "registered"


class PluginError(ValueError):
    """A fusion method registered from outside the built-ins that cannot be used: it cannot be imported, breaks
    the fusion contract, or its name is taken. The message (one line) names it, where it comes from and why."""


@dataclass
class Registration:
    """One name of the registry: what it points at, where it comes from, and (once loaded) its factory or why
    it cannot be used."""

    name: str
    kind: str  # "fusion" | "encoder"
    target: str  # "module:attribute"
    origin: str  # BUILTIN | ENTRY_POINT | REGISTERED
    modality: str | None = None  # encoders
    dist: str | None = None  # the distribution an entry point comes from: "NAME VERSION"
    entry_point: importlib.metadata.EntryPoint | None = None
    loaded: Any = None
    error: str | None = None  # the PluginError message, once it is known to be broken

    @property
    def builtin(self) -> bool:
        return self.origin == BUILTIN

    def where(self) -> str:
        if self.origin == ENTRY_POINT:
            return f"entry point {self.name} = {self.target} in group {FUSION_GROUP} of distribution {self.dist}"
        if self.origin == REGISTERED:
            return f"registered in-process: {self.target}"
        return f"built-in {self.target}"

    def source(self) -> str:
        """Where it comes from, short (the `v2vsim models` column)."""
        if self.origin == ENTRY_POINT:
            return f"plugin {self.dist}"
        return self.origin


_TABLES: dict[str, dict[str, Registration]] = {"fusion": {}, "encoder": {}}
_CLASHES: dict[str, list[Registration]] = {}  # a name already taken -> the entry points that claim it too
_scanned = False


def _builtin(kind: str, name: str, target: str, modality: str | None = None) -> None:
    _TABLES[kind][name] = Registration(name, kind, target, BUILTIN, modality=modality)


_builtin("encoder", "pointpillars", "models.pointpillars:build_pointpillars", "lidar")
_builtin("encoder", "sinbevt", "models.sinbevt:build_sinbevt", "camera")
_builtin("encoder", "lara", "models.lara:build_lara", "camera")
_builtin("fusion", "none", "models.fusion.none:NoFusion")
_builtin("fusion", "attfuse", "models.fusion.attfuse:AttFusion")
_builtin("fusion", "fcooper", "models.fusion.fcooper:FCooperFusion")
_builtin("fusion", "v2vnet", "models.fusion.v2vnet:V2VNetFusion")
_builtin("fusion", "disconet", "models.fusion.disconet:DiscoNetFusion")
_builtin("fusion", "cobevt", "models.fusion.cobevt:FuseBEVT")


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())[:300]


def _qualname(obj: Any) -> str:
    return f"{getattr(obj, '__module__', '?')}:{getattr(obj, '__qualname__', type(obj).__name__)}"


# ---- entry points ----------------------------------------------------------------------------------------------


def _scan() -> None:
    """Read the installed distributions' "v2vsim.fusion" entry points, once (names only: nothing is imported)."""
    global _scanned
    if _scanned:
        return
    _scanned = True
    table = _TABLES["fusion"]
    found: dict[str, Registration] = {}
    for ep in importlib.metadata.entry_points(group=FUSION_GROUP):
        dist = f"{ep.dist.name} {ep.dist.version}" if ep.dist is not None else "(an unnamed distribution)"
        reg = Registration(ep.name, "fusion", ep.value, ENTRY_POINT, dist=dist, entry_point=ep)
        label = f"fusion method {ep.name!r} ({reg.where()})"
        if ep.name in table or ep.name in BRACKETS:
            what = "built-in" if ep.name in BRACKETS or table[ep.name].builtin else "registered"
            reg.error = (f"{label}: its name clashes with the {what} method {ep.name!r}; rename the entry point "
                         "(or uninstall the distribution)")
            _CLASHES.setdefault(ep.name, []).append(reg)
        elif ep.name in RESERVED:
            reg.error = (f"{label}: {ep.name!r} is reserved (a `v2vsim train --stage` or zoo name: "
                         f"{', '.join(RESERVED)}); rename the entry point")
            found[ep.name] = reg
        elif ep.name in found:
            first = found[ep.name]
            first.error = (f"{label}: two installed distributions name a fusion method {ep.name!r}: this one and "
                           f"{first.where()}; uninstall one or rename its entry point")
        elif not METHOD_NAME.fullmatch(ep.name):
            reg.error = (f"{label}: {ep.name!r} is not a method name; allowed: lower-case letters, digits and '_', "
                         "starting with a letter, at most 32 characters (it goes into --methods lists and file names)")
            found[ep.name] = reg
        else:
            found[ep.name] = reg
    for name in sorted(found):
        table[name] = found[name]


def rescan_plugins() -> None:
    """Forget the entry points read so far (and what was loaded from them): the next question reads them again.
    For tests, and for a process that installed a plugin since it started."""
    global _scanned
    table = _TABLES["fusion"]
    for name in [n for n, r in table.items() if r.origin == ENTRY_POINT]:
        del table[name]
    _CLASHES.clear()
    _scanned = False


# ---- registering -----------------------------------------------------------------------------------------------


def register_fusion(name: str, factory: Callable[..., Any] | None = None) -> Any:
    """Register a fusion method by name: ``register_fusion("mine", Mine)`` or, on the class, ``@register_fusion(
    "mine")``. It is checked against the fusion contract now (PluginError if it breaks it, or if the name is
    taken or is no method name); returns the factory."""

    def add(f: Callable[..., Any]) -> Callable[..., Any]:
        _scan()
        reg = Registration(name, "fusion", _qualname(f), REGISTERED)
        if not isinstance(name, str) or not METHOD_NAME.fullmatch(name):
            raise PluginError(f"fusion method {name!r} ({reg.where()}): not a method name; allowed: lower-case "
                              "letters, digits and '_', starting with a letter, at most 32 characters")
        if name in RESERVED:
            raise PluginError(f"fusion method {name!r} ({reg.where()}): the name is reserved (a `v2vsim train "
                              f"--stage` or zoo name: {', '.join(RESERVED)})")
        taken = _TABLES["fusion"].get(name)
        if taken is not None or name in BRACKETS:
            what = "the built-in method" if taken is None or taken.builtin else taken.where()
            raise PluginError(f"fusion method {name!r} ({reg.where()}): its name clashes with {what} {name!r}")
        check_fusion_module(name, f, where=reg.where(), kwargs=_preset_kwargs(f, "tiny"))
        reg.loaded = f
        _TABLES["fusion"][name] = reg
        return f

    return add if factory is None else add(factory)


def unregister_fusion(name: str) -> None:
    """Remove a fusion method registered in-process or read from an entry point (never a built-in)."""
    reg = _TABLES["fusion"].get(name)
    if reg is None or reg.builtin:
        raise ValueError(f"{name!r} is no registered plugin" + (" (it is built in)" if reg is not None else ""))
    del _TABLES["fusion"][name]


def check_fusion_module(name: str, module_factory: Callable[..., Any], **kw: Any) -> None:
    """models.fusion.contract.check_fusion_module: PluginError unless the factory keeps the fusion contract."""
    from models.fusion.contract import check_fusion_module as check

    check(name, module_factory, **kw)


# ---- looking names up ------------------------------------------------------------------------------------------


def _known(kind: str, name: object) -> bool:
    if not isinstance(name, str):
        return False
    if name not in _TABLES[kind]:
        _scan()
    return name in _TABLES[kind]


def _names(kind: str) -> list[str]:
    _scan()
    return list(_TABLES[kind])


def _import(target: str) -> Any:
    module, _, attr = target.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def _resolve(reg: Registration) -> Any:
    """The registration's factory, imported (and, for an entry point, checked) the first time; PluginError if
    it cannot be used."""
    if reg.loaded is None and reg.error is None:
        label = f"fusion method {reg.name!r} ({reg.where()})"
        try:
            obj = reg.entry_point.load() if reg.entry_point is not None else _import(reg.target)
        except Exception as e:  # noqa: BLE001 - a plugin's import failure is reported, not raised through
            if reg.builtin:
                raise
            reg.error = f"{label}: cannot be imported: {type(e).__name__}: {_one_line(e)}"
        else:
            if reg.origin == ENTRY_POINT:
                try:
                    check_fusion_module(reg.name, obj, where=reg.where(), kwargs=_preset_kwargs(obj, "tiny"))
                except PluginError as e:
                    reg.error = str(e)
            if reg.error is None:
                reg.loaded = obj
    if reg.error is not None:
        raise PluginError(reg.error)
    return reg.loaded


def _preset_kwargs(obj: Any, preset: str) -> dict[str, Any]:
    kw = getattr(obj, "preset_kwargs", None) or {}
    return dict(kw.get(preset, {})) if isinstance(kw, Mapping) else {}


def fusion_names() -> list[str]:
    """Every fusion method's name: the built-ins, then those registered in-process and the installed plugins
    (broken ones too: requesting one raises its PluginError)."""
    return _names("fusion")


def method_names() -> list[str]:
    """Every method: the built-ins (BUILTIN_METHODS order), then the fusion methods registered from outside."""
    _scan()
    return [*BUILTIN_METHODS, *(n for n, r in _TABLES["fusion"].items() if not r.builtin)]


def encoder_names() -> list[str]:
    return list(_TABLES["encoder"])


def registration(name: str, kind: str = "fusion") -> Registration:
    """The Registration of a fusion method (or encoder) `name`; ValueError listing the names if unknown."""
    _check("fusion method" if kind == "fusion" else kind, name, FUSION if kind == "fusion" else ENCODERS)
    return _TABLES[kind][name]


def is_plugin(method: str) -> bool:
    """True for a fusion method from outside the built-ins (an entry point, or registered in-process)."""
    return _known("fusion", method) and not _TABLES["fusion"][method].builtin


def method_source(method: str) -> str:
    """Where a method comes from, short: "built-in", "plugin NAME VERSION" (its distribution) or "registered"."""
    _check("method", method, METHODS)
    reg = _TABLES["fusion"].get(method)
    return BUILTIN if reg is None else reg.source()


def check_methods(methods: Iterable[str]) -> None:
    """Load and check every plugin among `methods` (the fusion contract); PluginError for the first that cannot be
    used, or for a name an installed plugin claims although it is taken. Unknown names are the caller's to
    report (ValueError from is_intermediate & co)."""
    _scan()
    for m in methods:
        if m in _CLASHES:
            raise PluginError(_CLASHES[m][0].error)
        reg = _TABLES["fusion"].get(m)
        if reg is not None and not reg.builtin:
            _resolve(reg)


def broken_plugins() -> list[Registration]:
    """The fusion plugins that cannot be used, each with its PluginError message (loading every plugin)."""
    _scan()
    out = []
    for reg in [*_TABLES["fusion"].values(), *(r for rs in _CLASHES.values() for r in rs)]:
        if reg.builtin:
            continue
        try:
            _resolve(reg)
        except PluginError:
            out.append(reg)
    return out


def plugin_weights(method: str) -> Path | None:
    """The zoo folder a fusion plugin ships its checkpoints in (its object's `weights` attribute), if any."""
    if not is_plugin(method):
        return None
    w = getattr(_resolve(_TABLES["fusion"][method]), "weights", None)
    return None if w is None else Path(w)


def fusion_kwargs(name: str, preset: str) -> dict[str, Any]:
    """Keyword arguments (beyond `channels`) of fusion method `name` in model preset `preset`: the preset's
    (models.presets) for a built-in, the plugin's own `preset_kwargs[preset]` otherwise."""
    from models.presets import get_preset

    reg = registration(name)
    if reg.builtin:
        return get_preset(preset).fusion_args(name)
    return _preset_kwargs(_resolve(reg), preset)


# ---- views for existing callers: live, so that iterating them sees every plugin ------------------------------


class _NameList(Sequence[str]):
    """A read-only list of names computed from the registry on each use."""

    def __init__(self, names: Callable[[], list[str]], known: Callable[[object], bool]) -> None:
        self._names, self._known = names, known

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    def __getitem__(self, i: Any) -> Any:
        return self._names()[i]

    def __contains__(self, name: object) -> bool:
        return self._known(name)

    def __eq__(self, other: object) -> bool:
        if isinstance(other, (list, tuple, _NameList)):
            return list(self) == list(other)
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return repr(list(self))


class _View(Mapping[str, Any]):
    """A read-only mapping name -> value computed from the registry on each use (a plugin loads when looked up)."""

    def __init__(self, kind: str, value: Callable[[Registration], Any]) -> None:
        self._kind, self._value = kind, value

    def __getitem__(self, name: str) -> Any:
        if not _known(self._kind, name):
            raise KeyError(name)
        return self._value(_TABLES[self._kind][name])

    def __contains__(self, name: object) -> bool:
        return _known(self._kind, name)

    def __iter__(self) -> Iterator[str]:
        return iter(_names(self._kind))

    def __len__(self) -> int:
        return len(_names(self._kind))

    def __repr__(self) -> str:
        return f"<{self._kind} registry: {', '.join(self)}>"


def _method_known(name: object) -> bool:
    return isinstance(name, str) and (name in BUILTIN_METHODS or _known("fusion", name))


METHODS: Sequence[str] = _NameList(method_names, _method_known)
FUSION: Mapping[str, Callable[..., nn.Module]] = _View("fusion", _resolve)
ENCODERS: Mapping[str, Callable[..., nn.Module]] = _View("encoder", _resolve)
MODALITY: Mapping[str, str] = _View("encoder", lambda r: r.modality)


def _check(kind: str, name: str, allowed: Iterable[str]) -> None:
    if name not in allowed:
        raise ValueError(f"unknown {kind} {name!r}; allowed: {', '.join(allowed)}")


def is_intermediate(method: str) -> bool:
    """True for methods that fuse BEV feature messages (every FUSION entry but "none": plugins too)."""
    _check("method", method, METHODS)
    return method != "none" and method in _TABLES["fusion"]


def intermediate_methods() -> list[str]:
    """METHODS that fuse intermediate BEV features, in METHODS order (plugins last)."""
    return [m for m in METHODS if is_intermediate(m)]


def build_encoder(name: str, preset: str, bev_size_m: float = 100.0, cells: int | None = None,
                  image_backbone: str | None = None) -> nn.Module:
    """Encoder `name` ("pointpillars" | "sinbevt" | "lara") of `preset` -> [B, C, F, F] over bev_size_m.

    `cells`: the LiDAR fusion grid F (default the preset's; a zoo records its own, models.zoo.zoo_cells).
    The camera encoders' grid is fixed by their architecture (SinBEVT's output, Table A2): for them
    `cells` must be None or their own. `image_backbone`: a camera encoder's image backbone
    (models.image_backbone; default the preset's; a zoo records its own, models.zoo.zoo_image_backbone)."""
    from models.presets import get_preset

    _check("encoder", name, ENCODERS)
    p = get_preset(preset)
    if MODALITY[name] == "lidar":
        if image_backbone is not None:
            raise ValueError(f"{name}: a LiDAR encoder has no image backbone (got {image_backbone!r})")
        return ENCODERS[name](preset, bev_size_m=bev_size_m, cells=cells)
    if cells not in (None, p.camera_cells):
        raise ValueError(f"{name}: a camera encoder's grid is {p.camera_cells} x {p.camera_cells}, not {cells}")
    extra = {} if image_backbone is None else {"backbone": image_backbone}
    return ENCODERS[name](preset, bev_size_m=bev_size_m, **extra)


def preset_image_backbone(encoder: str, preset: str) -> str | None:
    """The image backbone (models.image_backbone) of a camera encoder's `preset`; None for a LiDAR encoder."""
    from models.lara import PRESETS as LARA_PRESETS
    from models.presets import get_preset
    from models.sinbevt import PRESETS as SINBEVT_PRESETS

    _check("encoder", encoder, ENCODERS)
    presets = {"sinbevt": SINBEVT_PRESETS, "lara": LARA_PRESETS}.get(encoder)
    return None if presets is None else presets[get_preset(preset).name].backbone


def build_fusion(name: str, preset: str) -> nn.Module:
    """Fusion module `name` of `preset`: forward([B, L, C, H, W], [B, L] bool) -> [B, C, H, W]."""
    from models.presets import get_preset

    _check("fusion method", name, FUSION)
    return FUSION[name](get_preset(preset).channels, **fusion_kwargs(name, preset))


def build_heads(modality: str, preset: str, in_cells: int | None = None) -> BevHeads:
    """Decoder + segmentation heads (+ detection head for "lidar") of `preset` for an in_cells grid (default:
    the preset's grid of that modality)."""
    from models.heads import build_bev_heads
    from models.presets import get_preset

    p = get_preset(preset)
    return build_bev_heads(modality, preset, in_cells or (p.cells if modality == "lidar" else p.camera_cells))


def build_cooperative(encoder: str, method: str, preset: str, bev_size_m: float = 100.0,
                      cells: int | None = None, image_backbone: str | None = None) -> CooperativePerception:
    """The whole model for one encoder and one of METHODS (brackets use fusion "none"); `cells`: the LiDAR
    fusion grid, `image_backbone`: a camera encoder's (build_encoder)."""
    from models.cooperative import CooperativePerception

    _check("encoder", encoder, ENCODERS)
    _check("method", method, METHODS)
    modality = MODALITY[encoder]
    fusion = build_fusion(method if is_intermediate(method) else "none", preset)
    enc = build_encoder(encoder, preset, bev_size_m, cells, image_backbone)
    return CooperativePerception(enc, fusion, build_heads(modality, preset, enc.out_cells), method, modality,
                                 bev_size_m)


def _params(m: nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def _hook_shapes(module: nn.Module, names: list[str], run: Callable[[], object]) -> list[tuple[str, tuple]]:
    """Run `run` with forward hooks on the named submodules; (name, output shape) in `names` order."""
    import torch

    shapes: dict[str, tuple] = {}
    subs = dict(module.named_modules())

    def make(n: str) -> Callable[..., None]:
        def hook(_m: nn.Module, _i: object, out: object) -> None:
            t = out[0] if isinstance(out, (tuple, list)) else out
            if isinstance(out, dict):
                t = next(iter(out.values()))
            if isinstance(t, torch.Tensor):
                shapes[n] = tuple(t.shape)

        return hook

    handles = [subs[n].register_forward_hook(make(n)) for n in names if n in subs]
    try:
        with torch.no_grad():
            run()
    finally:
        for h in handles:
            h.remove()
    return [(n, shapes[n]) for n in names if n in shapes]


def _row(name: str, kind: str, module: nn.Module, stages: list[tuple[str, tuple]], output: tuple | None,
         **extra: Any) -> dict:
    return {
        "name": name,
        "kind": kind,
        "params": _params(module),
        "stages": [{"stage": s, "shape": list(shape)} for s, shape in stages],
        "output": list(output) if output is not None else None,
        "origin": BUILTIN,
        **extra,
    }


def _with_output(module: nn.Module, run: Callable[[], list[tuple[str, tuple]]]) -> tuple[list, tuple | None]:
    """Run `run` (which calls module's forward) with a hook on the module itself; (its result, output shape)."""
    import torch

    seen: list[tuple] = []

    def hook(_m: nn.Module, _i: object, out: object) -> None:
        if isinstance(out, torch.Tensor):
            seen.append(tuple(out.shape))

    h = module.register_forward_hook(hook)
    try:
        stages = run()
    finally:
        h.remove()
    return stages, (seen[-1] if seen else None)


def describe_models(preset: str, agents: int = 4) -> list[dict]:
    """Every encoder, fusion method (plugins too) and the heads of `preset`: name, kind, origin (where it comes
    from: "built-in", "plugin NAME VERSION" (its distribution), "registered"), params, per-stage output shapes.

    Runs one forward pass per model on example inputs (encoders: their `example_inputs()`; fusion:
    `agents` random C x F x F maps; heads: the fused map) with forward hooks. A plugin that cannot be used is
    a row with "error" (its PluginError message) and no shapes: the listing shows it rather than fail.
    """
    import torch

    from models.presets import get_preset

    p = get_preset(preset)
    rows: list[dict] = []
    for name, modality in MODALITY.items():
        enc = build_encoder(name, preset).eval()
        stages, out = _with_output(enc, enc.stage_shapes)
        rows.append(_row(name, f"encoder ({modality})", enc, stages, out))
    feats = torch.randn(1, agents, p.channels, p.cells, p.cells)
    valid = torch.ones(1, agents, dtype=torch.bool)
    for name in fusion_names():
        reg = _TABLES["fusion"][name]
        try:
            fus = build_fusion(name, preset).eval()
        except PluginError as e:
            rows.append({"name": name, "kind": "fusion", "params": None, "stages": [], "output": None,
                         "origin": reg.source(), "error": str(e)})
            continue
        names = list(getattr(fus, "stage_names", [n for n, _ in fus.named_children()]))
        def run(fus: nn.Module = fus, names: list[str] = names) -> list[tuple[str, tuple]]:
            return _hook_shapes(fus, names, lambda: fus(feats, valid))

        stages, out = _with_output(fus, run)
        rows.append(_row(name, "fusion", fus, stages, out, agents=agents, origin=reg.source()))
    for name, regs in _CLASHES.items():  # installed plugins that claim a name already taken
        rows += [{"name": name, "kind": "fusion", "params": None, "stages": [], "output": None,
                  "origin": r.source(), "error": r.error} for r in regs]
    for modality in ("camera", "lidar"):
        heads = build_heads(modality, preset).eval()
        names = ["decoder.stages.0", "decoder.stages.1", "decoder.stages.2", "dynamic", "static"]
        if heads.detection is not None:
            names += ["detection.cls", "detection.reg"]
        x = torch.randn(1, p.channels, heads.in_cells, heads.in_cells)  # the fused map of that modality's grid
        stages = _hook_shapes(heads, names, lambda heads=heads, x=x: heads(x))
        rows.append(_row(f"heads-{modality}", "decoder+heads", heads, stages, dict(stages)["dynamic"]))
    for name in BRACKETS:  # the brackets: no module of their own
        rows.append({"name": name, "kind": "bracket", "params": 0, "stages": [], "output": None, "origin": BUILTIN})
    return rows


def format_models_table(rows: list[dict]) -> str:
    """Plain-text table of describe_models rows: name, kind, where it comes from, parameters, stage=shape ... ->
    output shape; a broken plugin's row says BROKEN and why."""

    def dims(shape: list[int]) -> str:
        return "x".join(str(d) for d in shape)

    notes = {"early": "raw points merged in the ego frame -> encoder -> heads",
             "late": "per-CAV outputs merged in the ego frame (max / rotated NMS)"}
    width = max([8, *(len(r.get("origin", BUILTIN)) for r in rows)])
    lines = [f"{'name':<14} {'kind':<18} {'from':<{width}} {'params':>12}  stages -> output"]
    for r in rows:
        parts = [f"{s['stage']}={dims(s['shape'])}" for s in r["stages"]]
        text = ", ".join(parts)
        if r.get("output") is not None:
            text = f"{text} -> {dims(r['output'])}" if text else f"-> {dims(r['output'])}"
        if r.get("error"):
            text = f"BROKEN: {r['error']}"
        params = "-" if r["params"] is None else f"{r['params']:,}"
        lines.append(f"{r['name']:<14} {r['kind']:<18} {r.get('origin', BUILTIN):<{width}} {params:>12}  "
                     f"{text or notes.get(r['name'], '-')}")
    return "\n".join(lines)
