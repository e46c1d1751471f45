"""Property-based fuzz of every user-written file's schema (issue 30), with hypothesis.

For each file kind — a ``--config`` TOML, a run's ``config.json``, an exported model's
``manifest.json``, a cell YAML and a sweep's ``sweep.json`` — a valid document shipped with the repo
is damaged at a generated place: a value of the wrong type, an out-of-range number, NaN or ±inf, a
key removed, an unknown key added (one to three damages at a time). The reader hydo itself uses is
given the result in this process (fast, so hundreds of cases each):

* it may accept the document only if the damage left it valid; a wrong type, NaN/inf or an unknown
  key is always refused, and so is a missing key the file must have;
* a refusal is one of the errors ``hydo`` turns into one line (``known_errors``), its message is one
  line and names the file;
* nothing else escapes (no ``TypeError`` from deep inside), and the file on disk is unchanged.

A few generated documents per kind then go through the real CLI as a subprocess: exit 1, exactly
one stderr line, no traceback, the user's files byte for byte as they were (``test_cli_*``).
The tests only use readers that existed before the schemas, so the same file runs against an older
checkout (docs/results.md records what it found on main).
"""

from __future__ import annotations

import copy
import json
import math
import shutil
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hydo_cli.errors import HydoError, known_errors
from tests.test_cli import hydo

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "hydo-cm-planar"
OLD_RUN = ROOT / "tests" / "data" / "old-run-v0"
CELL = ROOT / "robot" / "cell.example.yaml"
TOML_BASE = ROOT / "configs" / "planar-cube.toml"
#: Generated cases per file kind (in-process); the CLI cases are on top (``CLI_CASES``).
EXAMPLES = 150
CLI_CASES = 2

WRONG_TYPES = ("many", True, [1, 2], {"x": 1}, 1.5, 7)
NONFINITE = (math.nan, math.inf, -math.inf)
OUT_OF_RANGE = (-1, 0, -1e9, 1e12, 2**63)


# --- documents and damages ------------------------------------------------------------------------------


def paths_of(doc, prefix=()) -> list[tuple]:
    """Every key path into ``doc`` (mapping keys and list indices), parents before children."""
    out = []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        out.append((*prefix, k))
        out.extend(paths_of(v, (*prefix, k)))
    return out


def get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def kind_of(v) -> type:
    if isinstance(v, bool):
        return bool
    if isinstance(v, int | float):
        return float  # an integer where a number is expected is not a wrong type
    return type(v)


@st.composite
def damaged(draw, base: dict, free: tuple = (), str_accepts_int: bool = False):
    """``(document, must_refuse, why)``: ``base`` with one to three damages. ``free``: key prefixes
    of free-form records (anything goes inside them, they must only never crash the reader)."""
    doc = copy.deepcopy(base)
    must, why, done = False, [], []
    for _ in range(draw(st.integers(1, 3))):
        # never damage a place twice (a second wrong type may be the right one again)
        paths = [p for p in paths_of(doc) if not any(p[: len(d)] == d or d[: len(p)] == p for d in done)]
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent, key = get(doc, path[:-1]), path[-1]
        old = parent[key]
        checked = not any(path[: len(p)] == p for p in free)
        action = draw(st.sampled_from(["type", "nonfinite", "range", "missing", "unknown"]))
        if action == "type":
            wrong = [
                w
                for w in WRONG_TYPES
                if kind_of(w) is not kind_of(old)
                and not (isinstance(old, int) and not isinstance(old, bool) and isinstance(w, float))
                and not (str_accepts_int and isinstance(old, str) and type(w) in (int, float))
            ]
            if isinstance(old, float):  # 1.5 and 7 are numbers: not wrong for a float
                wrong = [w for w in wrong if kind_of(w) is not float]
            parent[key] = draw(st.sampled_from(wrong))
            must |= checked
        elif action == "nonfinite" and isinstance(old, int | float) and not isinstance(old, bool):
            parent[key] = draw(st.sampled_from(NONFINITE))
            must |= checked
        elif action == "range" and isinstance(old, int | float) and not isinstance(old, bool):
            parent[key] = draw(st.sampled_from(OUT_OF_RANGE))
        elif action == "missing" and isinstance(parent, dict):
            del parent[key]
        elif action == "unknown":
            target = old if isinstance(old, dict) else parent if isinstance(parent, dict) else doc
            target_path = path if isinstance(old, dict) else path[:-1] if isinstance(parent, dict) else ()
            target[draw(st.sampled_from(["stesp", "typo_key", "n_objs"]))] = 1
            must |= not any(target_path[: len(p)] == p and len(target_path) >= len(p) for p in free)
        else:
            continue
        done.append(path)
        why.append(f"{action} at {'.'.join(map(str, path))}")
    return doc, must, "; ".join(why)


def assert_refusal(e: BaseException, source: str) -> None:
    assert isinstance(e, known_errors()), f"{type(e).__name__} escaped: {e}"
    msg = str(e)
    assert "\n" not in msg.strip(), msg
    assert source in msg, (source, msg)


def check(read, doc_text: str | bytes, path: Path, must: bool, why: str) -> None:
    """Write the damaged document, give it to ``read``, check the property and the file."""
    data = doc_text.encode() if isinstance(doc_text, str) else doc_text
    path.write_bytes(data)
    try:
        read(path)
    except Exception as e:  # noqa: BLE001 - the property is about which exceptions escape
        assert_refusal(e, path.name)
    else:
        assert not must, f"accepted a damaged file ({why})"
    assert path.read_bytes() == data


# --- writers: TOML (no third-party writer: the config files are flat but for [agent]) ----------------


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def to_toml(doc: dict) -> str:
    lines = [f"{k} = {toml_value(v)}" for k, v in doc.items() if k != "agent"]
    if "agent" in doc:
        agent = doc["agent"]
        if isinstance(agent, dict):
            lines += ["[agent]", *(f"{k} = {toml_value(v)}" for k, v in agent.items())]
        else:
            lines.insert(0, f"agent = {toml_value(agent)}")
    return "\n".join(lines) + "\n"


# --- the five kinds: base document, reader, the CLI command that reads it ------------------------------


def toml_base() -> dict:
    import tomllib

    doc = tomllib.loads(TOML_BASE.read_text())
    doc["agent"] = {"actor_hidden": 16, "gamma": 0.99, "chain_entropy": "bound"}
    return doc


def read_toml(path: Path) -> None:
    from hydo_cli.config import agent_config, resolve_config

    agent_config(resolve_config(None, path, {}))  # what `hydo train` builds first


def read_config_json(path: Path) -> None:
    from hydo_cli.config import TrainConfig, agent_config

    agent_config(TrainConfig.load(path))


def read_manifest(path: Path) -> None:
    from robot.onnx_policy import read_manifest

    read_manifest(path.parent)  # what OnnxPolicy.load reads first (the graphs are beside it)


def read_cell(path: Path) -> None:
    from robot.cell import load_cell

    load_cell(path)


def read_sweep(path: Path) -> None:
    from hydo_cli.sweep import SweepSpec

    SweepSpec(path.parent, [], [], [], 1).load_state()


SWEEP_BASE = {
    "command": "hydo sweep --algos hydo-cm --seeds 0,1 --out runs/s",
    "trials": {
        "hydo-cm-s0": {"attempts": 1, "status": "done", "run": "runs/s/hydo-cm-s0", "returncode": 0},
        "hydo-cm-s1": {"attempts": 2, "status": "running", "run": "runs/s/hydo-cm-s1"},
    },
}

KINDS = {
    # name: (base document, serialise, reader, file name, free-form key prefixes)
    "config.toml": (toml_base, to_toml, read_toml, "train config.toml", ()),
    "config.json": (
        lambda: json.loads((OLD_RUN / "config.json").read_text()),
        json.dumps,
        read_config_json,
        "config.json",
        (),
    ),
    "manifest.json": (
        lambda: json.loads((MODEL / "manifest.json").read_text()),
        json.dumps,
        read_manifest,
        "manifest.json",
        (("verification",), ("agent_config",)),
    ),
    "cell.yaml": (lambda: yaml.safe_load(CELL.read_text()), yaml.safe_dump, read_cell, "céll file.yaml", ()),
    "sweep.json": (lambda: copy.deepcopy(SWEEP_BASE), json.dumps, read_sweep, "sweep.json", ()),
}


@pytest.mark.parametrize("kind", KINDS)
def test_base_documents_are_accepted(kind, tmp_path):
    """The property has teeth only if the undamaged document passes."""
    base, dump, read, name, _ = KINDS[kind]
    path = tmp_path / name
    if kind == "manifest.json":
        shutil.copytree(MODEL, tmp_path, dirs_exist_ok=True)
    path.write_text(dump(base()))
    read(path)


def _fuzz(kind: str, tmp_path_factory):
    base_fn, dump, read, name, free = KINDS[kind]
    base = base_fn()
    folder = tmp_path_factory.mktemp("fuzz dir ü")  # a space and a non-ASCII character in every path
    if kind == "manifest.json":
        for graph in ("encoder.onnx", "actor.onnx", "critic.onnx"):
            shutil.copy(MODEL / graph, folder / graph)

    @settings(
        max_examples=EXAMPLES,
        deadline=None,
        derandomize=True,  # the same cases on every run: a CI failure reproduces locally
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
        database=None,
    )
    @given(damaged(base, free=free, str_accepts_int=kind == "cell.yaml"))
    def run(case):
        doc, must, why = case
        try:
            text = dump(doc)
        except (TypeError, ValueError):  # e.g. a list at the TOML's top level mixed with tables
            return
        check(read, text, folder / name, must, why)

    run()


@pytest.mark.parametrize("kind", KINDS)
def test_fuzz(kind, tmp_path_factory):
    _fuzz(kind, tmp_path_factory)


# --- the real CLI on a few generated cases per kind ----------------------------------------------------


def cli_cases(kind: str) -> list[tuple[dict, str]]:
    """``CLI_CASES`` deterministic damages of ``kind`` that must be refused."""
    base_fn, _, _, _, free = KINDS[kind]
    found: list[tuple[dict, str]] = []

    @settings(max_examples=200, derandomize=True, database=None, deadline=None)
    @given(damaged(base_fn(), free=free, str_accepts_int=kind == "cell.yaml"))
    def collect(case):
        doc, must, why = case
        if must and len(found) < CLI_CASES and why not in [w for _, w in found]:
            found.append((doc, why))

    collect()
    return found


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def cli_setup(kind: str, doc: dict, tmp: Path) -> tuple[list, Path]:
    """Write ``doc`` where the command of ``kind`` reads it; ``(args, folder of the user's files)``."""
    _, dump, _, name, _ = KINDS[kind]
    if kind == "config.toml":
        (tmp / name).write_text(to_toml(doc))
        return ["train", "--config", tmp / name, "--out", tmp / "run ü"], tmp
    if kind == "config.json":
        run = tmp / "old run é"
        shutil.copytree(OLD_RUN, run)
        (run / "config.json").write_text(dump(doc))
        return ["train", "--resume", run], run
    if kind == "manifest.json":
        model = tmp / "model ü"
        shutil.copytree(MODEL, model)
        (model / "manifest.json").write_text(dump(doc))
        return ["eval", model, "--episodes", "1", "--json", tmp / "out.json"], model
    if kind == "cell.yaml":
        (tmp / name).write_text(dump(doc))
        return ["deploy", "--robot", "sim", "--model", MODEL, "--dry-run", "--cell", tmp / name], tmp
    out = tmp / "sweep ü"
    out.mkdir()
    (out / "sweep.json").write_text(dump(doc))
    return ["sweep", "--algos", "hydo-cm", "--seeds", "0", "--preset", "quick", "--out", out], out


@pytest.mark.parametrize("kind", KINDS)
def test_cli(kind, tmp_path):
    cases = cli_cases(kind)
    assert len(cases) == CLI_CASES
    for i, (doc, why) in enumerate(cases):
        tmp = tmp_path / f"case {i}"
        tmp.mkdir()
        args, user = cli_setup(kind, doc, tmp)
        before = snapshot(user)
        r = hydo(*args, cwd=tmp)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 1, (why, r.returncode, r.stderr[-2000:])
        assert "Traceback" not in r.stderr, (why, r.stderr[-2000:])
        assert len(lines) == 1 and lines[0].startswith("hydo: error: "), (why, r.stderr[-2000:])
        assert snapshot(user) == before, why


# --- the two cases of the issue, named ------------------------------------------------------------------


def test_issue_steps_many(tmp_path):
    """``steps = "many"`` in a --config TOML: one line naming the file and the key (was a traceback)."""
    from hydo_cli.config import resolve_config

    path = tmp_path / "bad.toml"
    path.write_text('steps = "many"\n')
    with pytest.raises(HydoError) as e:
        resolve_config(None, path, {})
    assert str(e.value) == f"{path}: `steps` must be an integer, got 'many'"


def test_issue_denoise_steps_against_the_actor(tmp_path):
    """A manifest that says K = 2 beside an actor unrolling 5 steps is refused (was deployed silently)."""
    from robot.errors import ModelLoadError
    from robot.onnx_policy import OnnxPolicy

    model = tmp_path / "model"
    shutil.copytree(MODEL, model)
    m = json.loads((model / "manifest.json").read_text())
    m["denoise_steps"] = 2
    (model / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelLoadError, match=r"`denoise_steps` 2 disagrees with `noise_per_point` 6"):
        OnnxPolicy.load(model)
    # the same K written into both keys: the graphs' own record (metadata_props) still says 5
    m["noise_per_point"] = 3
    del m["agent_config"]  # the record of the agent says 5 as well: leave only the graphs to tell
    (model / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelLoadError, match=r"exported with `denoise_steps` = 5, manifest.json says 2"):
        OnnxPolicy.load(model)
