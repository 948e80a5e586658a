"""ONE open registry of the names of encoders and fusion methods: what each name is, where it comes from, its
factory, and whether it is an intermediate method (models.build builds the models by these names).

Every encoder and fusion method is a `Registration` (models.registration) in this registry: the built-ins are
registered below (lazily, by "module:attribute", so that importing this module imports no torch and the scenario
checks stay light); code inside the package registers more with the `register_fusion` decorator; an installed
distribution adds fusion methods through Python entry points in group "v2vsim.fusion" (models.entry_points).

The entry points are read once, lazily, the first time the registry is asked for a name it does not know, for
the full list, or to check the methods a scenario requests (`check_methods`). A plugin's object is imported the
first time it is built or requested, and checked then against the fusion contract
(models.fusion.contract.check_fusion_module, models.fusion.base). Whatever goes wrong (it cannot be imported,
breaks the contract, its name is taken by a built-in or by another distribution, or is no method name) is a
PluginError naming the entry point, the object it points at and what it broke, raised whenever that name is
requested; `v2vsim models` (models.describe) lists it as broken with the reason.

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
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from models.declared import DeclaredMethod, read_declared
from models.entry_points import read_entry_points
from models.registration import (
    BRACKETS,
    BUILTIN,
    ENTRY_POINT,
    METHOD_NAME,
    REGISTERED,
    RESERVED,
    PluginError,
    Registration,
)

if TYPE_CHECKING:
    from torch import nn

# The built-in methods as their files in models/fusion/ declare them (models.declared: read, not imported).
DECLARED: dict[str, DeclaredMethod] = {m.name: m for m in read_declared(Path(__file__).parent / "fusion",
                                                                       "models.fusion")}
BUILTIN_METHODS = tuple(DECLARED)  # in rank order

_TABLES: dict[str, dict[str, Registration]] = {"fusion": {}, "encoder": {}}
_CLASHES: dict[str, list[Registration]] = {}  # a name already taken -> the entry points that claim it too
_scanned = False


def _builtin(kind: str, name: str, target: str, modality: str | None = None) -> None:
    _TABLES[kind][name] = Registration(name, kind, target, BUILTIN, modality=modality)


_builtin("encoder", "pointpillars", "models.pointpillars:build_pointpillars", "lidar")
_builtin("encoder", "sinbevt", "models.sinbevt:build_sinbevt", "camera")
_builtin("encoder", "lara", "models.lara:build_lara", "camera")
for _m in DECLARED.values():
    if not _m.bracket:
        _builtin("fusion", _m.name, _m.target)


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
    found, clashes = read_entry_points(_TABLES["fusion"])
    for name, regs in clashes.items():
        _CLASHES.setdefault(name, []).extend(regs)
    _TABLES["fusion"].update(found)


def name_clashes() -> list[Registration]:
    """The installed entry points that claim a fusion method's name already taken (each broken, saying so)."""
    _scan()
    return [r for regs in _CLASHES.values() for r in regs]


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
        _check_contract(name, f, where=reg.where(), kwargs=_preset_kwargs(f, "tiny"))
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


def _check_contract(name: str, module_factory: Callable[..., Any], **kw: Any) -> None:
    """models.fusion.contract.check_fusion_module (imported here: it imports torch): PluginError unless the
    factory keeps the fusion contract."""
    from models.fusion.contract import check_fusion_module

    check_fusion_module(name, module_factory, **kw)


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
                    _check_contract(reg.name, obj, where=reg.where(), kwargs=_preset_kwargs(obj, "tiny"))
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
    check_name("fusion method" if kind == "fusion" else kind, name, FUSION if kind == "fusion" else ENCODERS)
    return _TABLES[kind][name]


def is_plugin(method: str) -> bool:
    """True for a fusion method from outside the built-ins (an entry point, or registered in-process)."""
    return _known("fusion", method) and not _TABLES["fusion"][method].builtin


def method_source(method: str) -> str:
    """Where a method comes from, short: "built-in", "plugin NAME VERSION" (its distribution) or "registered"."""
    check_name("method", method, METHODS)
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
    """Keyword arguments (beyond `channels`) of fusion method `name` in model preset `preset`: its
    `preset_kwargs[preset]`, as its file declares them (a built-in, models.declared: read without importing it) or
    as the plugin's object carries them; ValueError for an unknown preset."""
    from models.presets import get_preset

    get_preset(preset)
    reg = registration(name)
    if reg.builtin:
        return dict(DECLARED[name].preset_kwargs.get(preset, {}))
    return _preset_kwargs(_resolve(reg), preset)


def paper_figures(method: str) -> tuple[tuple[float, float, float] | None, float | None]:
    """The CoBEVT paper's OPV2V figures for a built-in method (camera IoU vehicle / road / lane %, LiDAR
    AP@0.7), each None where the paper has none or the method is no built-in."""
    d = DECLARED.get(method)
    return (None, None) if d is None else (d.paper_camera_iou, d.paper_lidar_ap70)


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


def check_name(kind: str, name: str, allowed: Iterable[str]) -> None:
    """ValueError "unknown <kind> <name>; allowed: ..." unless `name` is among `allowed` (a registry view)."""
    if name not in allowed:
        raise ValueError(f"unknown {kind} {name!r}; allowed: {', '.join(allowed)}")


def is_intermediate(method: str) -> bool:
    """True for methods that fuse BEV feature messages (every FUSION entry but "none": plugins too)."""
    check_name("method", method, METHODS)
    return method != "none" and method in _TABLES["fusion"]


def intermediate_methods() -> list[str]:
    """METHODS that fuse intermediate BEV features, in METHODS order (plugins last)."""
    return [m for m in METHODS if is_intermediate(m)]
