"""The recording's default layout, sized for a laptop screen: the 3D world and the ground truth
large on the left with the ego's cameras; on the right every method's vehicle probability (one
tab) and errors (another) in a grid, the per-frame IoU and the V2V links as plots, and the
fusion log. Every view shares the time cursor (timeline `frame`)."""

from __future__ import annotations

import rerun.blueprint as rrb

from v2vsim.world.state import StaticMap


def _method_grid(methods: list[str], layer: str, name: str) -> rrb.Grid:
    views = [rrb.Spatial2DView(origin="bev", contents=[f"bev/{m}/{layer}", f"bev/{m}/boxes", "bev/gt/boxes"],
                               name=m) for m in methods]
    return rrb.Grid(*views, grid_columns=4 if len(methods) > 4 else 2, name=name)


def eye_over(static: StaticMap) -> rrb.EyeControls3D:
    """A steep view from the south onto the map centre (where the junction is), following the ego."""
    x0, y0, x1, y1 = static.bounds
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return rrb.EyeControls3D(position=[cx - 10.0, cy - 45.0, 75.0], look_target=[cx, cy, 0.0], eye_up=[0.0, 0.0, 1.0],
                             kind="Orbital", tracking_entity="world/ego")


def default_blueprint(methods: list[str], cameras: list[str], static: StaticMap, method_tab: int = 0,
                      closed_loop: bool = False) -> rrb.Blueprint:
    """method_tab: which of the method tabs is shown first (0 probability, 1 errors). closed_loop: a tab with the
    driven vehicle's speed, planned speed and closest gap (Recorder.log_drive)."""
    world = rrb.Spatial3DView(origin="world", name="world (3D: x east, y north, z up)", eye_controls=eye_over(static))
    gt = rrb.Spatial2DView(origin="bev", contents=["bev/gt/**"], name="ground truth (BEV, ego heading up)")
    cams = rrb.Grid(*[rrb.Spatial2DView(origin=f"world/ego_cameras/{c}", name=f"ego camera: {c}") for c in cameras],
                    grid_columns=2)
    plots = rrb.Tabs(
        rrb.TimeSeriesView(origin="metrics/iou_vehicle", name="vehicle IoU per frame",
                           plot_legend=rrb.PlotLegend(corner="LeftTop", visible=True)),
        rrb.TimeSeriesView(origin="links/latency_ms", name="link latency (ms)",
                           plot_legend=rrb.PlotLegend(corner="LeftTop", visible=True)),
        rrb.TimeSeriesView(origin="links/age_ms", name="age of fused messages (ms)",
                           plot_legend=rrb.PlotLegend(corner="LeftTop", visible=True)),
        rrb.TimeSeriesView(origin="links/delivered", name="link delivery (fraction so far)",
                           plot_legend=rrb.PlotLegend(corner="LeftBottom", visible=True)),
        *([rrb.TimeSeriesView(origin="drive", name="driving: speed, planned speed (m/s), closest gap (m)",
                              plot_legend=rrb.PlotLegend(corner="LeftTop", visible=True))] if closed_loop else []))
    left = rrb.Vertical(world, rrb.Horizontal(gt, cams, column_shares=[1, 1.3]), row_shares=[3, 2])
    right = rrb.Vertical(rrb.Tabs(_method_grid(methods, "probability", "vehicle probability"),
                                  _method_grid(methods, "errors", "errors (TP green, FP red, FN blue)"),
                                  active_tab=method_tab),
                         plots, rrb.TextLogView(origin="log", name="fusion log"), row_shares=[5, 3, 1.2])
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[1.1, 1]),
                         rrb.TimePanel(timeline="frame", play_state="paused", state="collapsed"), collapse_panels=True)
