"""Fusion plugins of installed distributions: their Python entry points in group "v2vsim.fusion" (FUSION_GROUP),
read into Registrations for the registry (models.registry):

    [project.entry-points."v2vsim.fusion"]
    maxfuse = "maxfuse:MaxFusion"

Reading them imports nothing (importlib.metadata: names and targets only); the registry does it once, lazily,
and imports and checks a plugin's object the first time it is built or requested. A name that cannot be used
here already (taken by a built-in or by another distribution, reserved, or no method name) becomes a
Registration with its PluginError message (`error`), raised whenever that name is requested.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Mapping

from models.registration import BRACKETS, ENTRY_POINT, FUSION_GROUP, METHOD_NAME, RESERVED, Registration


def read_entry_points(taken: Mapping[str, Registration]
                      ) -> tuple[dict[str, Registration], dict[str, list[Registration]]]:
    """The installed distributions' "v2vsim.fusion" entry points, against the fusion methods already `taken`
    (the built-ins and those registered in-process): (name -> its Registration, in name order; a name already
    taken -> the entry points that claim it too). Two distributions naming one method: the first is kept, broken,
    saying so."""
    found: dict[str, Registration] = {}
    clashes: dict[str, list[Registration]] = {}
    for ep in importlib.metadata.entry_points(group=FUSION_GROUP):
        dist = f"{ep.dist.name} {ep.dist.version}" if ep.dist is not None else "(an unnamed distribution)"
        reg = Registration(ep.name, "fusion", ep.value, ENTRY_POINT, dist=dist, entry_point=ep)
        label = f"fusion method {ep.name!r} ({reg.where()})"
        if ep.name in taken or ep.name in BRACKETS:
            what = "built-in" if ep.name in BRACKETS or taken[ep.name].builtin else "registered"
            reg.error = (f"{label}: its name clashes with the {what} method {ep.name!r}; rename the entry point "
                         "(or uninstall the distribution)")
            clashes.setdefault(ep.name, []).append(reg)
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
    return {name: found[name] for name in sorted(found)}, clashes
