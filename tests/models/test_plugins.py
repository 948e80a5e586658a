"""The open registry (models.registry) and the fusion contract check (models.fusion.contract): fusion methods
registered in-process and through entry points ("installed" into a folder on sys.path: tests/conftest.py
fake_site), checked when they load, seen by every view of the registry; a broken one named with what it broke."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest
import torch
from torch import nn

from models import registry
from models.build import build_cooperative, build_fusion
from models.fusion.cobevt import FuseBEVT
from models.fusion.contract import check_fusion_module
from models.registration import PluginError
from models.registry import (
    FUSION,
    METHODS,
    check_methods,
    fusion_kwargs,
    intermediate_methods,
    is_intermediate,
    is_plugin,
    method_source,
    register_fusion,
    unregister_fusion,
)

GOOD = '''
import torch
from torch import nn


class MaxMix(nn.Module):
    preset_kwargs = {"tiny": {"scale": 0.5}}

    def __init__(self, channels, scale=1.0):
        super().__init__()
        self.scale = scale
        self.mix = nn.Conv2d(channels, channels, 1)

    def forward(self, features, valid_mask):
        neg = torch.full((), float("-inf"), dtype=features.dtype)
        return self.mix(torch.where(valid_mask[:, :, None, None, None], features, neg).amax(dim=1)) * self.scale
'''

BROKEN = '''
import torch
from torch import nn


class WrongShape(nn.Module):
    def __init__(self, channels):
        super().__init__()

    def forward(self, features, valid_mask):
        return features[:, 0, :4]


class Peeks(nn.Module):
    def __init__(self, channels):
        super().__init__()

    def forward(self, features, valid_mask):
        return features.mean(dim=1)


def fails(channels):
    raise RuntimeError("needs a GPU")
'''


# ---- the contract check ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["none", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt"])
def test_every_builtin_keeps_the_contract(name: str) -> None:
    check_fusion_module(name, FUSION[name], kwargs=fusion_kwargs(name, "tiny"))


class _Mean(nn.Module):  # reads every slot: absent agents change the output
    def forward(self, f: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return f.mean(1)


class _Masked(nn.Module):  # excludes absent agents by multiplying with the mask: 0 * NaN = NaN
    def forward(self, f: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return (f * v[:, :, None, None, None]).sum(1)


class _Channels(nn.Module):
    def forward(self, f: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return f[:, 0, :3]


class _Double(nn.Module):
    def forward(self, f: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return f[:, 0].double()


class _Tuple(nn.Module):
    def forward(self, f: torch.Tensor, v: torch.Tensor) -> tuple:
        return f[:, 0], v


class _NeedsNeighbours(nn.Module):  # fails on a frame with the ego alone (L = 1)
    def forward(self, f: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return f[:, 0] + f[:, 1] * 0


class _Inf(nn.Module):
    def forward(self, f: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return f[:, 0] / 0


def _raises(channels: int) -> nn.Module:
    raise RuntimeError("no such layer")


@pytest.mark.parametrize(("factory", "what"), [
    (lambda c: _Mean(), "the output changes when an absent agent's features change"),
    (lambda c: _Masked(), "NaN / inf in an absent agent's features reach the output"),
    (lambda c: _Channels(), "shape (3, 3, 16, 16); expected a float32 tensor [B, C, H, W] = (3, 64, 16, 16)"),
    (lambda c: _Double(), "returned a float64 tensor"),
    (lambda c: _Tuple(), "returned a tuple"),
    (lambda c: _NeedsNeighbours(), "the ego alone) raised IndexError"),
    (lambda c: _Inf(), "non-finite values"),
    (_raises, "cannot be built as _raises(64): RuntimeError: no such layer"),
    (lambda c: object(), "not a torch.nn.Module"),
])
def test_a_broken_module_is_named_with_what_it_broke(factory, what: str) -> None:
    with pytest.raises(PluginError) as e:
        check_fusion_module("mine", factory, where="entry point mine = pkg:Mine")
    msg = str(e.value)
    assert msg.startswith("fusion method 'mine' (entry point mine = pkg:Mine): ") and what in msg, msg
    assert "models/fusion/base.py" in msg and "\n" not in msg


def test_the_check_leaves_the_random_state_alone() -> None:
    """A seeded run builds the same weights whether or not a plugin was checked in that process first."""
    torch.manual_seed(3)
    check_fusion_module("fcooper", FUSION["fcooper"])
    after = torch.rand(4)
    torch.manual_seed(3)
    assert torch.equal(after, torch.rand(4))


# ---- registering in-process ---------------------------------------------------------------------------------------


class _Plain(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.mix = nn.Conv2d(channels, channels, 1)

    def forward(self, f: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return self.mix(torch.where(v[:, :, None, None, None], f, torch.zeros(())).sum(1))


@pytest.fixture
def registered() -> Iterator[str]:
    register_fusion("plainsum")(_Plain)
    try:
        yield "plainsum"
    finally:
        unregister_fusion("plainsum")


def test_a_registered_method_is_seen_everywhere(registered: str) -> None:
    assert list(METHODS)[-1] == registered and registered in METHODS and registered in FUSION
    assert FUSION[registered] is _Plain and is_intermediate(registered) and is_plugin(registered)
    assert intermediate_methods()[-1] == registered and method_source(registered) == "registered"
    assert not is_plugin("cobevt") and method_source("cobevt") == "built-in"
    model = build_cooperative("pointpillars", registered, "tiny")
    assert isinstance(model.fusion, _Plain) and model.method == registered
    unregister_fusion(registered)
    assert registered not in METHODS
    register_fusion(registered, _Plain)  # (the fixture unregisters it)


@pytest.mark.parametrize(("name", "what"), [
    ("cobevt", "clashes with the built-in method 'cobevt'"),
    ("late", "clashes with the built-in method 'late'"),
    ("cache", "the name is reserved"),
    ("Max-Fuse", "not a method name"),
])
def test_a_taken_or_bad_name_is_refused(name: str, what: str) -> None:
    with pytest.raises(PluginError, match=what):
        register_fusion(name, _Plain)
    assert FUSION["cobevt"] is FuseBEVT


def test_a_broken_module_is_refused_when_it_registers() -> None:
    try:
        with pytest.raises(PluginError, match="'peeks' .*absent agent"):
            register_fusion("peeks", lambda c: _Mean())
        assert "peeks" not in METHODS
    finally:
        if "peeks" in METHODS:
            unregister_fusion("peeks")


# ---- entry points ------------------------------------------------------------------------------------------------


def test_entry_points_are_read_lazily_and_checked_when_used(fake_site) -> None:
    fake_site.install("goodplug", "goodplug_mod", GOOD, {"maxmix": "goodplug_mod:MaxMix"})
    assert "maxmix" in METHODS and "maxmix" in list(FUSION) and is_intermediate("maxmix")
    assert "goodplug_mod" not in sys.modules  # names only: nothing imported yet
    assert method_source("maxmix") == "plugin goodplug 0.1"
    fusion = build_fusion("maxmix", "tiny")  # imported, checked, built with its preset_kwargs
    assert type(fusion).__name__ == "MaxMix" and fusion.scale == 0.5
    assert build_fusion("maxmix", "paper").scale == 1.0
    check_methods(["none", "maxmix", "cobevt"])


def test_a_broken_entry_point_names_itself_and_what_it_broke(fake_site) -> None:
    fake_site.install("brokenplug", "brokenplug_mod", BROKEN, {
        "wrongshape": "brokenplug_mod:WrongShape", "peeks": "brokenplug_mod:Peeks", "fails": "brokenplug_mod:fails",
        "missing": "brokenplug_mod:Nowhere"})
    assert {"wrongshape", "peeks", "fails", "missing"} <= set(METHODS)  # known (listed), unusable
    expect = {"wrongshape": "returned a float32 tensor of shape (3, 4, 16, 16)",
              "peeks": "the output changes when an absent agent's features change",
              "fails": "cannot be built as fails(64): RuntimeError: needs a GPU",
              "missing": "cannot be imported: AttributeError"}
    for name, what in expect.items():
        for call, args in ((check_methods, (["none", name],)), (build_fusion, (name, "tiny")),
                           (build_cooperative, ("pointpillars", name, "tiny"))):
            with pytest.raises(PluginError) as e:
                call(*args)
            msg = str(e.value)
            assert f"entry point {name} = brokenplug_mod:" in msg and "distribution brokenplug 0.1" in msg, msg
            assert what in msg, msg
    assert {r.name for r in registry.broken_plugins()} == set(expect)
    check_methods(["none", "cobevt"])  # the others still work


def test_an_entry_point_may_not_take_a_builtin_name(fake_site) -> None:
    fake_site.install("clashplug", "clashplug_mod", GOOD, {"cobevt": "clashplug_mod:MaxMix",
                                                           "single": "clashplug_mod:MaxMix"})
    with pytest.raises(PluginError, match=r"'cobevt' \(entry point cobevt = clashplug_mod:MaxMix .*clashplug 0.1\): "
                                          "its name clashes with the built-in method 'cobevt'"):
        check_methods(["none", "cobevt"])
    with pytest.raises(PluginError, match="'single' is reserved"):
        check_methods(["single"])
    assert FUSION["cobevt"] is FuseBEVT  # never replaced
    assert {r.name for r in registry.broken_plugins()} == {"cobevt", "single"}


def test_two_distributions_may_not_name_the_same_method(fake_site) -> None:
    fake_site.install("twina", "twina_mod", GOOD, {"twin": "twina_mod:MaxMix"})
    fake_site.install("twinb", "twinb_mod", GOOD, {"twin": "twinb_mod:MaxMix"})
    with pytest.raises(PluginError, match="two installed distributions name a fusion method 'twin'"):
        check_methods(["twin"])
