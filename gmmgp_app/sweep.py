"""Map one scan for several values of one config field (``gmmgp sweep``, whose command
line is :mod:`gmmgp_app.commands.sweep`).

Every value is one step on the ``sweep`` timeline of a single rerun recording
(stages as in :mod:`gmmgp_app.viz.rerun_observer`, the scene is cleared between
values), with per-value metrics under ``sweep/metrics/{name}`` (value, leaves,
gp_points, gp_blocks, vertices, seconds and, with a reference, rmse_sdf and
surface_rmse) and a Markdown table under ``sweep/table``. The same table is
written as JSON.

RMSE with ``--reference`` (a mesh, or a dense cloud, see
:meth:`gmmgp_app.evaluation.Reference.load`; in the scan's original frame):

* ``rmse_sdf``: signed distance RMSE at query points within +-0.5 m of the
  surface (:func:`gmmgp_app.evaluation.sample_queries` along the normals of the
  first value's training points, seed 0, the same queries for every value);
* ``surface_rmse``: RMS of the reference distance at the extracted mesh vertices.
"""

from __future__ import annotations

import time

import numpy as np

from .pipeline import FanoutObserver

__all__ = ["SweepError", "parse_values", "run_sweep", "table_markdown"]

#: Queries for rmse_sdf.
N_QUERIES = 20000


class SweepError(ValueError):
    """Bad sweep request (no values, or a value the config field rejects)."""


def parse_values(param: str, values: str, base=None) -> list:
    """Parse ``--values`` for ``--param`` and validate every value up front.

    Parameters
    ----------
    param : str
        Dotted config field, e.g. ``hgmm.split_threshold``.
    values : str
        Comma separated values, each parsed as TOML (``0.01``, ``8``, ``true``,
        ``"covariance"`` or a bare word).
    base : MappingConfig, optional

    Returns
    -------
    list of the parsed values, in order.
    """
    from .config import MappingConfig, parse_value

    base = MappingConfig() if base is None else base
    raw = [v.strip() for v in str(values).split(",") if v.strip()]
    if not raw:
        raise SweepError(f"Expected --values as a comma separated list like 0.005,0.01,0.02, "
                         f"found {values!r}.")
    parsed = [parse_value(v) for v in raw]
    for v in parsed:
        base.replace(param, v)  # raises ConfigError naming the field and the value
    return parsed


def _scalar(x):
    if isinstance(x, (np.generic,)):
        return x.item()
    return x


class _Collect:
    """Keeps the prepared training set of a run (for the evaluation queries)."""

    def __init__(self):
        self.data = None

    def on_stage(self, name, payload):
        if name == "prepare":
            self.data = payload.result


def table_markdown(param: str, rows: list) -> str:
    cols = [c for c in ("leaves", "gp_points", "gp_blocks", "vertices", "rmse_sdf",
                        "surface_rmse", "seconds") if any(c in r for r in rows)]
    lines = [f"# Sweep of `{param}`", "", "| step | value | " + " | ".join(cols) + " |",
             "|---:|---:|" + "---:|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c)
            cells.append("" if v is None else (f"{v:.4g}" if isinstance(v, float) else f"{v:,}"))
        lines.append(f"| {r['step']} | {r['value']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run_sweep(scan, param: str, values: list, *, base=None, method: str = "gmmgp",
              rrd=None, reference=None, mesh: bool = True, console=None,
              n_queries: int = N_QUERIES) -> list:
    """Build one map per value of ``param`` and record them on a ``sweep`` timeline.

    Parameters
    ----------
    scan : Scan
    param : str
        Dotted config field.
    values : list
        Already parsed values (see :func:`parse_values`).
    base : MappingConfig, optional
    method : str
        One of :data:`gmmgp_app.config.METHODS`.
    rrd : path, optional
        Recording to write (one file, every value a step on ``sweep``).
    reference : Reference, optional
        Ground truth in the scan's original frame; adds ``rmse_sdf`` and
        ``surface_rmse``.
    mesh : bool
        Extract the marching-cubes surface of each map.
    console : observer, optional
        Progress output.
    n_queries : int

    Returns
    -------
    list of dict, one per value: step, value, leaves, gp_points, gp_blocks,
    vertices, seconds (total and per stage), rmse_sdf, surface_rmse (with a
    reference).
    """
    from .config import MappingConfig
    from .evaluation import evaluate_field, sample_queries
    from .pipeline import StagePayload, build_map

    base = MappingConfig() if base is None else base
    if not values:
        raise SweepError("Expected at least one value to sweep, found none.")
    obs = None
    if rrd is not None:
        import rerun as rr

        from .viz.rerun_observer import RerunObserver, default_blueprint

        obs = RerunObserver(rrd, config=None, application_id="gmmgp_sweep",
                            blueprint=default_blueprint("sweep", sweep=True),
                            timelines={"sweep": 0})
        md = (f"# Sweep of `{param}`\n\nValues (one per step of the `sweep` timeline): "
              f"{', '.join(str(v) for v in values)}\n\n## Base configuration\n\n```toml\n"
              + base.to_toml() + "```\n")
        obs.log("config", rr.TextDocument(md, media_type="text/markdown"), static=True)
    rows: list = []
    queries = None
    offset = scan.offset
    for i, value in enumerate(values):
        cfg = base.replace(param, value)
        collect = _Collect()
        if obs is not None:
            obs.config = cfg
            obs.extra_time["sweep"] = i
            obs.summary = {"seconds": {}, "counts": {}}
            obs.set_time(stage=0)
            # A value may log fewer levels or no GP: clear the previous value's scene.
            obs.log("world", obs.rr.Clear(recursive=True))
        t0 = time.perf_counter()
        smap = build_map(scan, cfg, method=method,
                         observer=FanoutObserver(console, obs, collect))
        row = {"step": i, "value": _scalar(value), "param": param}
        seconds = dict(smap.summary.get("seconds", {}))
        if smap.hgmm is not None:
            row["leaves"] = int(smap.hgmm.leaves.n_components)
            row["levels"] = len(smap.hgmm.levels)
        row["gp_points"] = len(smap.gp_points)
        if smap.gp is not None:
            row["gp_blocks"] = int(smap.gp.grid.n_blocks)
        surface = None
        if mesh:
            ts = time.perf_counter()
            surface = smap.extract_surface()
            seconds["surface"] = time.perf_counter() - ts
            row["vertices"] = len(surface.vertices)
            row["faces"] = len(surface.faces)
            if obs is not None:
                obs.on_stage("surface", StagePayload({method: surface}, seconds["surface"]))
        row["seconds"] = time.perf_counter() - t0
        row["stage_seconds"] = {k: float(v) for k, v in seconds.items()}
        if reference is not None:
            if queries is None and collect.data is not None and len(collect.data.points):
                queries = sample_queries(collect.data.points, collect.data.normals, n_queries,
                                         rng=np.random.default_rng(0))
                train = collect.data.points

            def shifted(xyz, _r=reference):
                return _r.sdf(np.asarray(xyz) + offset)

            if queries is not None:
                ref_local = type(reference)(shifted, reference.kind, reference.description)
                m = evaluate_field(smap.predict, ref_local, queries, train)
                row["rmse_sdf"] = float(m["all"]["rmse_sdf"])
                row["ll_sdf"] = float(m["all"]["ll_sdf"])
            if surface is not None and len(surface.vertices):
                d = shifted(surface.vertices)
                row["surface_rmse"] = float(np.sqrt(np.mean(d ** 2)))
        rows.append(row)
        if obs is not None:
            obs.set_time(stage=None)  # sweep metrics live on the sweep timeline only
            for k in ("leaves", "gp_points", "gp_blocks", "vertices", "rmse_sdf",
                      "surface_rmse", "seconds"):
                if k in row:
                    obs.scalar(f"sweep/metrics/{k}", row[k])
            if isinstance(row["value"], (int, float)) and not isinstance(row["value"], bool):
                obs.scalar("sweep/metrics/value", row["value"])
            obs.log("sweep/table", obs.rr.TextDocument(table_markdown(param, rows),
                                                       media_type="text/markdown"))
            obs.flush()
    if obs is not None:
        obs.close()
    return rows
