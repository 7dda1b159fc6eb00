"""The incident's PNG: angle, velocity, torque and CiA 402 state of every drive around it,
drawn from the states its JSON carries (``python -m motor_driver.recording INCIDENT.json``, a
helper process at low priority).

What the driver did not know is drawn as missing: a sample of a drive lost or stale carries no
values (``null`` in the JSON, NaN on the plot, a gap in its line), never its last values again.
The state axis names the CiA 402 states.

Owner: the helper process's one thread (its drawing); no state kept.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from motor_driver.drive import DriveState
from motor_driver.protocol.cia402 import State

#: The series of one drive in the summary, in the order of the plot's axes.
SERIES = ("angle_deg", "velocity_deg_s", "torque_nm", "state")
LABELS = ("angle, deg", "velocity, deg/s", "torque, Nm", "CiA 402 state")


def state_series(states: list[tuple[float, tuple[DriveState, ...]]], t0: float) -> dict[str, Any]:
    """The drives' states as series per drive, times in s from the incident; a drive whose values
    the driver's verdict did not take as measured (lost, late, re-booting, not configured), or a
    torque it does not report, is ``None``: missing, not its last value."""
    series: dict[str, dict[str, list[float | None]]] = {}
    for t, snap in states:
        for s in snap:
            row = series.setdefault(s.name, {"t_s": [], **{key: [] for key in SERIES}})
            row["t_s"].append(round(t - t0, 4))
            known = s.verdict.fresh
            row["angle_deg"].append(round(s.angle_deg, 4) if known else None)
            row["velocity_deg_s"].append(round(s.velocity_deg_s, 3) if known else None)
            row["torque_nm"].append(s.torque_nm if known and not math.isnan(s.torque_nm) else None)
            row["state"].append(int(s.state) if known else None)
    return series


def plotted(row: dict[str, list[Any]], key: str) -> list[float]:
    """One series as drawn: a missing value is NaN (a gap in the line)."""
    return [math.nan if v is None else float(v) for v in row[key]]


def draw(summary: dict[str, Any], where: str) -> Any:
    """The incident's figure (a matplotlib Figure; ``where`` names the summary in an error);
    ValueError says why there is nothing to draw."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    states = summary.get("states") or {}
    if not states:
        raise ValueError(f"{where}: no drive states recorded around the incident: nothing to plot"
                         " (its frames are in the .blf and .mcap beside it)")
    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    for name, row in states.items():
        for ax, key in zip(axes, SERIES, strict=True):
            ax.plot(row["t_s"], plotted(row, key), label=name, marker="." if key == "state" else None,
                    drawstyle="steps-post" if key == "state" else "default")
    for ax, label in zip(axes, LABELS, strict=True):
        ax.set_ylabel(label)
        ax.axvline(0.0, color="red", linewidth=0.8)
        ax.grid(True)
    axes[3].set_yticks([int(s) for s in State], [state_label(s) for s in State], fontsize="x-small")
    axes[0].legend(fontsize="small", loc="upper left")
    first = summary["events"][0]
    axes[0].set_title(f"{first['kind']} {first.get('drive') or first['bus']} {first.get('text', '')}"
                      " (gaps: the drive lost or stale)")
    axes[-1].set_xlabel("s from the incident")
    fig.tight_layout()
    return fig


def state_label(state: State) -> str:
    return state.name.replace("_", " ").lower()


def plot_incident(json_path: Path) -> Path:
    """Draw ``<stem>.png`` from an incident's summary; ValueError says why it cannot be drawn."""
    import matplotlib.pyplot as plt

    fig = draw(json.loads(json_path.read_text()), str(json_path))
    png = json_path.with_suffix(".png")
    fig.savefig(png)
    plt.close(fig)
    return png


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m motor_driver.recording INCIDENT.json``: draw its PNG, at low priority; when it
    cannot, say why."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        print("usage: python -m motor_driver.recording INCIDENT.json", file=sys.stderr)
        return 2
    try:
        os.nice(10)
    except OSError:
        pass
    try:
        png = plot_incident(Path(args[0]))
    except ImportError:
        print("no matplotlib: no plot (pip install rovercan[cli])", file=sys.stderr)
        return 1
    except (OSError, ValueError, KeyError, IndexError) as err:  # a missing or damaged summary
        print(f"no plot: {err}", file=sys.stderr)
        return 1
    print(png)
    return 0
