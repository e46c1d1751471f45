"""The sim → twin ladder (``hydo deploy ladder``): where an exported policy's success is lost.

One model runs the same episodes (``sim.goals.episode_seed``: same object, start and goal) on five
rungs, each adding one difference between training and the robot cell:

=============  ===============================================================================
``env``        the training env: floating hand teleported to ``p + 0.04·n`` and stopped at 30 N,
               mesh observations of what the cameras see
``env-render`` the training env with rendered depth, background subtraction and PCA normals
``twin-true``  the twin of the cell (``robot.twin``): the full arm and its impedance controller,
               force stop and reflexes, observed through the true pose and mesh (as in training)
``twin-cameras`` the twin observed through its cameras and segmentation (the deploy cloud and its
               PCA normals), with the true transform to the goal in place of registration
``twin``       the twin with the full deploy pipeline: cameras, segmentation, registration
=============  ===============================================================================

The policy samples its motions, so each rung's success is one draw of that sampling on its
episodes; the ``env`` rung is also rerun with ``env_draws - 1`` other draws (policy seeds
``seed + 1000·k``, a few seconds each) and reports their mean and range: the yardstick's own spread
(±2-3 points on 100 episodes), against which a lower rung's loss is read.

Per rung: success by the true poses, mean final distance (the reward's mean goal flow), and what
ended the failed episodes (``near_miss``: the step limit with the object within 3-4.5 cm; the step
limit further away; the object leaving the bin; refusals by kind; the twin's reflex limit), with
refused primitives, force stops and reflexes. Against the previous rung: episodes lost and gained.
The ``twin`` rung also scores the deploy loop's own verdict (``robot.loop``, from registration)
against the truth: agreement, false successes (of which symmetric-pose confusions: ADD-S under 1 cm
with ADD over 2 cm), false failures and ambiguous verdicts.

With ``jobs`` processes, each twin rung's episodes are also split into ``jobs`` contiguous pieces,
one twin session each (``LOG/<rung>/e000-049``, ...), and merged back in episode order: a twin
episode is the same whichever session runs it (its object, start, goal, noise and samples come from
``(seed, episode)``, and the twin's simulation state is fresh each episode), so the figures do not
depend on ``jobs``.
"""

from __future__ import annotations

import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

RUNGS = {
    "env": "training env: floating hand, mesh observations",
    "env-render": "training env: rendered depth + PCA normals",
    "twin-true": "twin: full arm, true pose and mesh",
    "twin-cameras": "twin: full arm, cameras + segmentation, true pose for the goal flow",
    "twin": "twin: full arm, cameras + segmentation + registration",
}
NEAR_MISS_M = 0.045  # a step-limit episode that ended within 3-4.5 cm of the goal is a near miss
SYMMETRIC_ADDS_M = 0.01  # registration to a symmetric pose: ADD-S under this ...
SYMMETRIC_ADD_M = 0.02  # ... with ADD over this


@dataclass
class LadderEpisode:
    object: str
    success: bool  # by the true poses (the training env's own verdict, the twin's true one)
    final_distance: float  # m, mean goal flow of the surface samples at the end (true poses)
    steps: int  # primitives
    cause: str  # "success" | "near_miss" | "step_limit" | "object_left_bin" | "reflex_limit" | refusal
    reported: str | None = (
        None  # twin with cameras: the deploy loop's verdict (success | failure | ambiguous)
    )
    symmetric: bool = False  # twin with cameras: its last registration picked a symmetric pose


@dataclass
class RungResult:
    rung: str
    description: str
    episodes: list[LadderEpisode]
    refused_primitives: int = 0  # training env: primitives refused (scene unchanged, episode goes on)
    force_stops: int = 0
    reflexes: int = 0
    mean_registration_adds_m: float | None = None
    n_registrations: int = 0  # the twin rung's registrations that mean is over
    seconds: float = 0.0  # process seconds (a rung split into pieces: theirs summed)
    extra: dict = field(default_factory=dict)

    def summary(self) -> dict:
        eps = self.episodes
        out = {
            "rung": self.rung,
            "description": self.description,
            "episodes": len(eps),
            "success_rate": float(np.mean([e.success for e in eps])) if eps else 0.0,
            "mean_final_distance_m": float(np.mean([e.final_distance for e in eps])) if eps else 0.0,
            "causes": dict(sorted(Counter(e.cause for e in eps if not e.success).items())),
            "refused_primitives": self.refused_primitives,
            "force_stops": self.force_stops,
            "reflexes": self.reflexes,
            "seconds": round(self.seconds, 1),
        }
        reported = [e for e in eps if e.reported is not None]
        if reported:
            decided = [e for e in reported if e.reported != "ambiguous"]
            agree = [e for e in decided if (e.reported == "success") == e.success]
            false_success = [e for e in decided if e.reported == "success" and not e.success]
            out["verdict"] = {
                "reported_success_rate": float(np.mean([e.reported == "success" for e in reported])),
                "agreement": len(agree) / len(decided) if decided else None,
                "ambiguous": sum(e.reported == "ambiguous" for e in reported),
                "false_success": len(false_success),
                "false_success_symmetric": sum(e.symmetric for e in false_success),
                "false_failure": sum(e.reported == "failure" and e.success for e in decided),
                "mean_registration_adds_m": self.mean_registration_adds_m,
            }
        out.update(self.extra)
        return out


def _cause_from_distance(cause: str, success: bool, distance: float) -> str:
    if success:
        return "success"
    if cause in ("timeout", "step_limit", "success"):  # "success": reported, not true (twin verdicts)
        return "near_miss" if distance < NEAR_MISS_M else "step_limit"
    return cause


def run_env_rung(
    rung: str, model: Path, n: int, seed: int, objects: str, goals: str, env_draws: int = 1
) -> RungResult:
    """``env`` / ``env-render``: the training env (``hydo eval``'s episodes) with the ONNX policy;
    ``env``: also ``env_draws - 1`` other draws of the policy's sampling on the same episodes."""
    from hydo_cli.envs import make_envs
    from hydo_cli.policies import load_onnx_policy
    from hydo_cli.rollout import run_episodes

    def episodes(policy_seed: int) -> list:
        loaded = load_onnx_policy(model, policy_seed)
        obs = "render" if rung == "env-render" else "mesh"
        envs = make_envs(objects, goals, 0, obs, 1, loaded.n_obj, loaded.n_bg)
        try:
            return run_episodes(envs, loaded.policy, n, seed)
        finally:
            for e in envs:
                e.close()

    t0 = time.perf_counter()
    results = episodes(seed)  # hydo eval's draw: the policy seeded as the episodes
    seconds = time.perf_counter() - t0
    extra = {}
    if rung == "env" and env_draws > 1:
        rates = [float(np.mean([r.success for r in results]))]
        rates += [float(np.mean([r.success for r in episodes(seed + 1000 * k)])) for k in range(1, env_draws)]
        extra = {
            "policy_draws": rates,
            "policy_draws_mean": float(np.mean(rates)),
            "policy_draws_s": round(time.perf_counter() - t0 - seconds, 1),
        }
    eps = [
        LadderEpisode(
            r.object,
            r.success,
            r.final_distance,
            r.steps,
            _cause_from_distance(r.failure, r.success, r.final_distance),
        )
        for r in results
    ]
    return RungResult(
        rung,
        RUNGS[rung],
        eps,
        refused_primitives=sum(r.rejected for r in results),
        force_stops=sum(r.force_stops for r in results),  # the training hand's stop (FORCE_STOP_N)
        seconds=seconds,
        extra=extra,
    )


def run_twin_rung(
    rung: str,
    model: Path,
    n: int,
    seed: int,
    objects: str,
    log_dir: Path,
    registration: str = "auto",
    first: int = 0,
) -> RungResult:
    """``twin-true`` / ``twin-cameras`` / ``twin``: ``hydo deploy --robot sim`` on the same episodes
    (``robot.loop``), episodes ``first`` … ``first + n - 1`` of ``seed``; ``registration``: the
    ``twin`` rung's (``auto`` | ``views`` | ``model``)."""
    from robot.loop import DeployConfig, Deployment
    from robot.report import write_summary

    t0 = time.perf_counter()
    cfg = DeployConfig(
        robot="sim",
        model=model,
        episodes=n,
        first_episode=first,
        seed=seed,
        log_dir=log_dir,
        objects=objects,
        perception={"twin-true": "true", "twin-cameras": "cameras-true-pose"}.get(rung, "cameras"),
        registration=registration,
        command=f"hydo deploy ladder (rung {rung})",
    )
    dep = Deployment.prepare(cfg)
    res = dep.run()
    write_summary(res)  # the session folder reads like any `hydo deploy` session's
    last_step = {}
    for s in res.steps:  # the episode's last observation: its registration decided the verdict
        last_step[s.episode] = s
    eps = []
    for e in res.episodes:
        true_success = bool(e.true_success)
        d = float(e.true_distance) if e.true_distance is not None else float("nan")
        reported = None
        symmetric = False
        if rung == "twin":
            reported = "success" if e.success else "failure"
            if e.cause == "ambiguous":
                reported = "ambiguous"
            s = last_step.get(e.episode)
            if s is not None and s.registration_error is not None and s.registration_add is not None:
                symmetric = s.registration_error < SYMMETRIC_ADDS_M and s.registration_add > SYMMETRIC_ADD_M
        eps.append(
            LadderEpisode(
                e.object,
                true_success,
                d,
                e.steps,
                _cause_from_distance(e.cause, true_success, d),
                reported,
                symmetric,
            )
        )
    adds = [s.registration_error for s in res.steps if s.registration_error is not None]
    extra = {}
    if rung == "twin":
        extra["registration"] = dep.cfg.registration  # what "auto" chose for this model
        extra["steps_refused_by_kind"] = dict(
            Counter(s.outcome for s in res.steps if s.outcome.endswith(("Error", "Rejected")))
        )
    result = RungResult(
        rung,
        RUNGS[rung],
        eps,
        force_stops=res.force_stops,
        reflexes=res.reflexes,
        mean_registration_adds_m=float(np.mean(adds)) if adds and rung == "twin" else None,
        n_registrations=len(adds) if rung == "twin" else 0,
        seconds=time.perf_counter() - t0,
        extra=extra,
    )
    return result


def twin_pieces(n: int, parts: int) -> list[tuple[int, int]]:
    """``(first, count)`` of up to ``parts`` contiguous pieces of episodes ``0 … n - 1``, whose sizes
    differ by at most one."""
    parts = max(1, min(parts, n))
    sizes = [n // parts + (i < n % parts) for i in range(parts)]
    return [(sum(sizes[:i]), size) for i, size in enumerate(sizes)]


def merge_pieces(pieces: list[RungResult]) -> RungResult:
    """One rung from the results of its pieces, given in episode order."""
    if len(pieces) == 1:
        return pieces[0]
    n_reg = sum(p.n_registrations for p in pieces)
    extra = dict(pieces[0].extra)
    if "steps_refused_by_kind" in extra:
        refused: Counter = Counter()
        for p in pieces:
            refused.update(p.extra["steps_refused_by_kind"])
        extra["steps_refused_by_kind"] = dict(refused)
    extra["pieces"] = len(pieces)
    return RungResult(
        pieces[0].rung,
        pieces[0].description,
        [e for p in pieces for e in p.episodes],
        refused_primitives=sum(p.refused_primitives for p in pieces),
        force_stops=sum(p.force_stops for p in pieces),
        reflexes=sum(p.reflexes for p in pieces),
        mean_registration_adds_m=(
            sum(p.mean_registration_adds_m * p.n_registrations for p in pieces if p.n_registrations) / n_reg
            if n_reg
            else None
        ),
        n_registrations=n_reg,
        seconds=sum(p.seconds for p in pieces),
        extra=extra,
    )


def _run_rung(args) -> RungResult:
    rung, model, first, n, seed, objects, goals, log_dir, registration, env_draws = args
    if rung.startswith("env"):
        return run_env_rung(rung, model, n, seed, objects, goals, env_draws)
    return run_twin_rung(rung, model, n, seed, objects, log_dir, registration, first)


def run_ladder(
    model: Path,
    episodes: int,
    seed: int,
    log_dir: Path,
    rungs: tuple[str, ...] = tuple(RUNGS),
    objects: str | None = None,
    jobs: int = 2,
    registration: str = "auto",
    env_draws: int = 1,
) -> list[RungResult]:
    """Run ``rungs`` of the ladder for an exported ``model`` in ``jobs`` processes (each twin rung
    split into ``jobs`` pieces of its episodes); returns them in ladder order. Twin sessions are
    logged under ``log_dir/<rung>`` (``log_dir/<rung>/eFFF-LLL`` per piece); ``registration``: the
    ``twin`` rung's (``hydo deploy --registration``); ``env_draws``: draws of the policy's sampling
    on the ``env`` rung (the first is the one its episodes are compared on)."""
    import json

    manifest = json.loads((Path(model) / "manifest.json").read_text())
    objects = objects or str(manifest.get("objects") or "train")
    goals = str(manifest.get("goals", "6d"))
    tasks = []
    for r in rungs:  # the env rungs are a minute or two: whole; the twin's ~8 s an episode: split
        pieces = [(0, episodes)] if r.startswith("env") else twin_pieces(episodes, jobs)
        for first, n in pieces:
            folder = Path(log_dir) / r
            if len(pieces) > 1:
                folder = folder / f"e{first:03d}-{first + n - 1:03d}"
            tasks.append((r, Path(model), first, n, seed, objects, goals, folder, registration, env_draws))
    if jobs <= 1:
        done = [_run_rung(t) for t in tasks]
    else:
        # slowest first (the twin with cameras), so the processes finish close together
        order = sorted(range(len(tasks)), key=lambda i: -list(RUNGS).index(tasks[i][0]))
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            futures = {i: pool.submit(_run_rung, tasks[i]) for i in order}
            done = [futures[i].result() for i in range(len(tasks))]
    return [merge_pieces([d for t, d in zip(tasks, done, strict=True) if t[0] == r]) for r in rungs]


def compare_rungs(results: list[RungResult]) -> list[dict]:
    """Per rung: its summary, with episodes lost and gained against the previous rung (same episodes)."""
    out = []
    prev = None
    for r in results:
        s = r.summary()
        if prev is not None and len(prev.episodes) == len(r.episodes):
            s["lost_vs_previous"] = sum(
                a.success and not b.success for a, b in zip(prev.episodes, r.episodes, strict=True)
            )
            s["gained_vs_previous"] = sum(
                b.success and not a.success for a, b in zip(prev.episodes, r.episodes, strict=True)
            )
        out.append(s)
        prev = r
    return out


def ladder_json(results: list[RungResult], command: str, model: Path, seed: int) -> dict:
    return {
        "command": command,
        "model": str(model),
        "seed": seed,
        "rungs": compare_rungs(results),
        "episodes": {r.rung: [asdict(e) for e in r.episodes] for r in results},
    }
