"""``hydo deploy review SESSION``: what an operator looks at when a deploy episode went wrong.

One row per step of a session folder (``robot.session_log``; ``hydo deploy --log``): the camera
depth with the segmentation mask, the fused cloud seen from above with object points coloured by
their goal-flow length, the chosen contact point and the planned push path (fingertip waypoints),
and the safety gate's verdict with the step's outcome. Everything comes from what the session
already records: ``steps/eNNN-sNN.npz`` (depth in 0.1 mm, masks, clouds, observation, action,
waypoints) and ``log.jsonl`` (``observation``, ``plan``, ``refused``, ``outcome``, ``episode_end``).
Written as a PNG strip (or .pdf/.svg) or, with an ``.mp4`` name, a video of one frame per step.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console

from hydo_cli.errors import HydoError
from hydo_cli.figures import check_image_path, require_matplotlib, save_figure
from hydo_cli.paths import check_writable

HELP = """Review a deploy session: per step the camera depth with the segmentation mask, the fused cloud
coloured by goal-flow length with the chosen contact point and planned push path, the safety verdict
and the outcome.

SESSION is a `hydo deploy --log` folder. --out session.png writes one strip (a row per step);
session.mp4 a video (a frame per step). Needs the plot extra: pip install -e '.[plot]'.

Example:

  hydo deploy review runs/deploy/session --out session.png --episode 0
"""

console = Console(stderr=True)
STEP_FILE = re.compile(r"e(\d{3})-s(\d{2})\.npz$")
ROW_HEIGHT_IN = 3.0


@dataclass
class Step:
    """One recorded observation of a session and what the log says happened after it."""

    episode: int
    step: int
    path: Path
    events: dict[str, dict] = field(default_factory=dict)  # observation / plan / refused / outcome

    def verdict(self) -> str:
        if "refused" in self.events:
            e = self.events["refused"]
            return f"REFUSED {e.get('error', '')}: {e.get('message', '')}"
        if "plan" in self.events:
            return f"plan passed the gate (joint margin {self.events['plan'].get('min_joint_margin_rad', '?')} rad)"
        return "no plan (goal reached or step limit)"

    def outcome(self) -> str:
        if "outcome" in self.events:
            o = self.events["outcome"]
            extra = (
                f", peak force {o['peak_force_n']:.1f} N" if isinstance(o.get("peak_force_n"), float) else ""
            )
            return f"outcome: {o.get('outcome', '?')}{extra}"
        return "outcome: not executed"


def load_steps(session: Path, episode: int | None) -> tuple[list[Step], dict[int, dict]]:
    """The session's steps in order (of ``episode`` only, if given) and each episode's end event."""
    from robot.session_log import read_log, session_folders

    pieces = session_folders(session)
    if len(pieces) > 1:  # a ladder rung split over processes: the session that played the episode
        played = [
            p for p in pieces if episode is not None and any((p / "steps").glob(f"e{episode:03d}-s*.npz"))
        ]
        if not played:
            names = ", ".join(p.name for p in pieces)
            raise HydoError(
                f"SESSION {session} holds {len(pieces)} sessions ({names}): give one, or --episode N"
            )
        session = played[0]
    if not (session / "log.jsonl").is_file() or not (session / "steps").is_dir():
        raise HydoError(f"SESSION {session} is not a deploy session folder (no log.jsonl and steps/)")
    steps = {}
    for p in sorted((session / "steps").glob("e*-s*.npz")):
        m = STEP_FILE.search(p.name)
        if m and (episode is None or int(m[1]) == episode):
            steps[(int(m[1]), int(m[2]))] = Step(int(m[1]), int(m[2]), p)
    ends = {}
    for e in read_log(session):
        key = (e.get("episode"), e.get("step"))
        if key in steps and e["event"] in ("observation", "plan", "refused", "outcome"):
            steps[key].events[e["event"]] = e
        if e["event"] == "episode_end":
            ends[e["episode"]] = e
    if not steps:
        which = f" of episode {episode}" if episode is not None else ""
        raise HydoError(f"SESSION {session} has no recorded steps{which}")
    return [steps[k] for k in sorted(steps)], ends


def _depth_panel(ax, npz) -> None:
    """The camera whose mask holds the most object pixels: depth (m) with the mask outlined in red."""
    serials = [k.split("/", 1)[1] for k in npz.files if k.startswith("depth/")]
    masks = {s: npz[f"mask/{s}"] for s in serials if f"mask/{s}" in npz.files}
    serial = max(masks, key=lambda s: masks[s].sum()) if masks else serials[0]
    depth = npz[f"depth/{serial}"].astype(np.float32) * 1e-4  # stored in 0.1 mm (robot.session_log)
    depth[depth == 0] = np.nan  # holes
    im = ax.imshow(depth, cmap="viridis")
    if serial in masks and masks[serial].any():
        overlay = np.zeros((*masks[serial].shape, 4))
        overlay[masks[serial]] = (1.0, 0.1, 0.1, 0.55)
        ax.imshow(overlay)
    ax.set_title(f"{serial}: depth (m), mask in red", fontsize=8)
    ax.axis("off")
    ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02)


def _cloud_panel(ax, npz) -> None:
    """Top-down fused cloud (x, y in the base frame, m): background grey, object points by goal-flow
    length (m); the contact point and the fingertip's planned path."""
    if "bg_points" in npz.files and len(npz["bg_points"]):
        bg = npz["bg_points"]
        ax.scatter(bg[:, 0], bg[:, 1], s=1, c="0.75", lw=0)
    if "features" in npz.files:  # the observation the policy saw: features = [is_object, goal_flow xyz]
        pts, feat = npz["points"], npz["features"]
        obj = feat[:, 0] > 0.5
        flow = np.linalg.norm(feat[obj, 1:4], axis=1)
        sc = ax.scatter(pts[obj, 0], pts[obj, 1], s=6, c=flow, cmap="plasma", lw=0)
        ax.figure.colorbar(sc, ax=ax, fraction=0.046, pad=0.02, label="goal flow (m)")
    elif "obj_points" in npz.files and len(npz["obj_points"]):
        obj = npz["obj_points"]
        ax.scatter(obj[:, 0], obj[:, 1], s=2, c="tab:orange", lw=0)
    if "waypoints" in npz.files:
        w = npz["waypoints"]
        ax.plot(w[:, 0], w[:, 1], "-o", color="tab:blue", ms=2, lw=1.2, label="planned path")
        ax.annotate("", xy=w[-1, :2], xytext=w[-2, :2], arrowprops=dict(arrowstyle="->", color="tab:blue"))
    if "action_index" in npz.files and "points" in npz.files:
        p = npz["points"][int(npz["action_index"])]
        ax.scatter([p[0]], [p[1]], marker="*", s=140, c="lime", edgecolors="black", lw=0.6, label="contact")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("fused cloud from above (x, y m)", fontsize=8)
    ax.tick_params(labelsize=7)


def _text_panel(ax, s: Step, end: dict | None, last: bool) -> None:
    obs = s.events.get("observation", {})
    reg = obs.get("registration", {})
    lines = [f"episode {s.episode}, step {s.step}"]
    if reg:
        lines.append(f"registered distance to goal {100 * reg.get('distance_m', float('nan')):.1f} cm")
        lines.append(f"registration rmse {1000 * reg.get('rmse_m', float('nan')):.1f} mm")
    if obs.get("n_object_points") is not None:
        lines.append(f"object points {obs['n_object_points']}")
    verdict = s.verdict()
    lines += ["", verdict, s.outcome()]
    if last and end is not None:
        lines += ["", f"episode: {'SUCCESS' if end.get('success') else 'no success'} {end.get('reason', '')}"]
    colour = "firebrick" if verdict.startswith("REFUSED") else "black"
    ax.text(0.0, 1.0, "\n".join(lines), va="top", ha="left", fontsize=8, color=colour, wrap=True)
    ax.axis("off")


def step_figure(steps: list[Step], ends: dict[int, dict], session: Path):
    """A figure of ``len(steps)`` rows x 3 panels (depth + mask | cloud + contact + path | verdict)."""
    Figure = require_matplotlib()
    fig = Figure(figsize=(13, ROW_HEIGHT_IN * len(steps)))
    axes = np.atleast_2d(fig.subplots(len(steps), 3, gridspec_kw={"width_ratios": [1.2, 1.2, 0.9]}))
    for k, s in enumerate(steps):
        with np.load(s.path) as npz:
            _depth_panel(axes[k, 0], npz)
            _cloud_panel(axes[k, 1], npz)
        last = k + 1 == len(steps) or steps[k + 1].episode != s.episode
        _text_panel(axes[k, 2], s, ends.get(s.episode), last)
    fig.suptitle(f"deploy session {session.name}", y=1.0)
    fig.tight_layout()
    return fig


def review(
    session: Annotated[Path, typer.Argument(help="Session folder (hydo deploy --log).", show_default=False)],
    out: Annotated[
        Path,
        typer.Option("--out", help="session.png: a strip, a row per step; session.mp4: a frame per step."),
    ] = Path("session.png"),
    episode: Annotated[int | None, typer.Option("--episode", help="Only this episode.")] = None,
    max_steps: Annotated[int, typer.Option("--max-steps", help="At most this many steps (the first).")] = 50,
) -> None:
    is_video = out.suffix.lower() == ".mp4"
    if not is_video:
        check_image_path("--out", out)
    check_writable("--out", out)
    if max_steps < 1:
        raise HydoError("--max-steps must be at least 1")
    if not session.is_dir():
        raise HydoError(f"SESSION {session} is not a folder: give a `hydo deploy --log` folder")
    steps, ends = load_steps(session, episode)
    steps = steps[:max_steps]
    if is_video:
        from sim.video import write_video

        frames = []
        for s in steps:
            from matplotlib.backends.backend_agg import FigureCanvasAgg

            canvas = FigureCanvasAgg(step_figure([s], ends, session))  # one size for every frame
            canvas.draw()
            frames.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
        write_video(frames, out, fps=1)
    else:
        save_figure(step_figure(steps, ends, session), out)
    console.print(f"wrote {out} ({len(steps)} steps of {len({s.episode for s in steps})} episodes)")
