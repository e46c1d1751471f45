"""The results of a deploy session: what each step and episode measured, and how it is reported.

:class:`StepRecord` (one observation, decision and execution), :class:`EpisodeResult`,
:class:`SessionResult` (with :meth:`SessionResult.summary`, the figures written to
``summary.json``), :func:`summary_lines` (the rows of the table ``hydo deploy`` prints) and
:func:`write_summary`. The twin-only fields (mask IoU, registration error, true-pose distance and
success) stay ``None`` on a real arm; ``robot.twin_metrics`` measures them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FLOW_OFF_M = 0.01  # summary: a step's flow off the true one by this much (ADD on the object's surface)


@dataclass
class StepRecord:
    episode: int
    step: int
    distance: float  # m, measured by registration
    rmse: float
    inliers: float
    n_object_points: int
    outcome: str = ""  # the plan's outcome, "dry-run", "success" or the refusal class
    seconds: float = 0.0  # wall time of the whole step
    perception_s: float = 0.0
    registration_s: float = 0.0
    policy_s: float = 0.0
    execution_s: float = 0.0
    iou: float | None = None  # twin: mask IoU vs ground truth (pooled over cameras)
    registration_error: float | None = None  # twin: ADD-S (m) of the estimated vs true transform
    registration_add: float | None = None  # twin: ADD (m), symmetric poses counted as errors
    true_distance: float | None = None  # twin: mean goal flow from the true poses (training's)


@dataclass
class EpisodeResult:
    episode: int
    success: bool  # measured (registration distance < 3 cm)
    steps: int  # primitives executed (or planned, in a dry run)
    distance: float | None  # last measured distance, m
    reason: str = ""  # why it ended without success
    object: str = ""
    true_success: bool | None = None  # twin: from the true poses
    true_distance: float | None = None
    # how it ended: "success" | "step_limit" | "object_left_bin" | "reflex_limit" (twin) | the class
    # name of the refusal that ended it (PerceptionError, RegistrationError, PrimitiveRejected, ...)
    cause: str = ""


@dataclass
class SessionResult:
    folder: Path
    episodes: list[EpisodeResult] = field(default_factory=list)
    steps: list[StepRecord] = field(default_factory=list)
    commands_sent: int = 0
    force_stops: int = 0  # contact-force stops (reaction_fired): an outcome of a step
    reflexes: int = 0  # robot reflexes, each recovered once or ending the run
    reflex_limit_episodes: int = 0  # twin: episodes ended by the recovery limits (a real arm stops)

    def summary(self) -> dict:
        def mean(xs):
            xs = [x for x in xs if x is not None]
            return float(np.mean(xs)) if xs else None

        eps = self.episodes
        # time per step: the steps that planned a primitive (not the episodes' final observations)
        timed = [s for s in self.steps if s.policy_s > 0]
        return {
            "episodes": len(eps),
            "success_rate": mean([float(e.success) for e in eps]),
            "true_success_rate": mean(
                [None if e.true_success is None else float(e.true_success) for e in eps]
            ),
            "primitives": sum(e.steps for e in eps),
            "mean_iou": mean([s.iou for s in self.steps]),
            "mean_registration_error_m": mean([s.registration_error for s in self.steps]),
            # the flow's transform off the true one by 1 cm or more on the object's surface (ADD): a
            # symmetric or nearly symmetric goal pose that reads the same distance but moves each
            # point elsewhere than training's flow would
            "flow_off_1cm": mean(
                [
                    None if s.registration_add is None else float(s.registration_add >= FLOW_OFF_M)
                    for s in self.steps
                ]
            ),
            "mean_registration_rmse_m": mean([s.rmse for s in self.steps]),
            "mean_step_s": mean([s.seconds for s in timed]),
            "mean_perception_s": mean([s.perception_s for s in self.steps]),
            "mean_registration_s": mean([s.registration_s for s in self.steps]),
            "mean_policy_s": mean([s.policy_s for s in timed]),
            "mean_execution_s": mean([s.execution_s for s in timed if s.execution_s > 0]),
            "commands_sent": self.commands_sent,
            "force_stops": self.force_stops,
            "reflexes": self.reflexes,
            "reflex_limit_episodes": self.reflex_limit_episodes,
            # registration cannot tell whether it is within 3 cm: neither a success nor a failure
            "ambiguous_episodes": sum(e.cause == "ambiguous" for e in eps),
        }


def summary_lines(res: SessionResult) -> list[tuple[str, str]]:
    """(name, value) rows of the final table."""
    s = res.summary()

    def pct(v):
        return "n/a" if v is None else f"{v:.0%}"

    def ms(v):
        return "n/a" if v is None else f"{v * 1000:.0f} ms"

    rows = [
        ("episodes", str(s["episodes"])),
        ("success rate (registration)", pct(s["success_rate"])),
    ]
    if s["ambiguous_episodes"]:
        rows.append(("ambiguous (not counted as success)", str(s["ambiguous_episodes"])))
    if s["true_success_rate"] is not None:
        rows.append(("success rate (twin, true poses)", pct(s["true_success_rate"])))
    rows.append(("primitives", str(s["primitives"])))
    if s["mean_iou"] is not None:
        rows.append(("segmentation IoU (twin)", f"{s['mean_iou']:.3f}"))
    if s["mean_registration_error_m"] is not None:
        rows.append(("registration error ADD-S (twin)", f"{s['mean_registration_error_m'] * 1000:.1f} mm"))
    if s["flow_off_1cm"] is not None:
        rows.append(("flows off the true one by 1 cm+ (ADD, twin)", pct(s["flow_off_1cm"])))
    if s["mean_registration_rmse_m"] is not None:
        rows.append(("registration inlier RMS", f"{s['mean_registration_rmse_m'] * 1000:.1f} mm"))
    rows += [
        ("time per step", "n/a" if s["mean_step_s"] is None else f"{s['mean_step_s']:.2f} s"),
        ("  perception", ms(s["mean_perception_s"])),
        ("  registration", ms(s["mean_registration_s"])),
        ("  policy (onnxruntime)", ms(s["mean_policy_s"])),
        ("  execution", "n/a" if s["mean_execution_s"] is None else f"{s['mean_execution_s']:.2f} s"),
        ("motion commands sent", str(s["commands_sent"])),
        ("contact-force stops", str(s["force_stops"])),
        ("reflexes", str(s["reflexes"])),
    ]
    if s["reflex_limit_episodes"]:
        rows.append(("episodes ended by the reflex limit (twin)", str(s["reflex_limit_episodes"])))
    rows += [
        ("session folder", str(res.folder)),
    ]
    return rows


def write_summary(res: SessionResult) -> None:
    (res.folder / "summary.json").write_text(json.dumps(res.summary(), indent=2))
