"""The README's commands stay runnable: CI runs its test command verbatim, and every ``hydo`` command,
option, repository file and bench script its fenced bash blocks name exists; its links resolve."""

import glob
import os
import re
import shlex
import subprocess
import sys
import tomllib
from functools import cache
from pathlib import Path

import pytest
import typer

from hydo_cli.main import app

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: Options whose value is a file the command writes, not one that must already exist.
OUTPUT_OPTIONS = {"--out", "--json", "--markdown", "--video", "--log", "--plot"}
#: Top-level folders of repository files a command may read.
REPO_DIRS = ("configs/", "robot/", "models/", "bench/", "sim/", "docs/")


def bash_commands(text: str) -> list[list[str]]:
    """Every simple command of the fenced bash blocks, as tokens (comments dropped, split on && ; |)."""
    commands = []
    for block in re.findall(r"^```bash\n(.*?)^```", text, re.S | re.M):
        for line in block.splitlines():
            current: list[str] = []
            for tok in shlex.split(line, comments=True):
                if tok in {"&&", "||", ";", "|"}:
                    commands.append(current)
                    current = []
                else:
                    current.append(tok)
            commands.append(current)
    return [c for c in commands if c]


def split_hydo(tokens: list[str]) -> tuple[tuple[str, ...], list[str]]:
    """``hydo deploy capture-goal --robot panda`` -> (("deploy", "capture-goal"), ["--robot", "panda"])."""
    cmd = typer.main.get_command(app)
    path: list[str] = []
    rest = tokens[1:]
    while rest and getattr(cmd, "commands", None) and rest[0] in cmd.commands:
        cmd = cmd.commands[rest[0]]
        path.append(rest[0])
        rest = rest[1:]
    return tuple(path), rest


HYDO = [split_hydo(c) for c in bash_commands(README) if c[0] == "hydo"]


@cache
def hydo_help(path: tuple[str, ...]) -> subprocess.CompletedProcess:
    """``hydo <path> --help`` through the real console entry point, wide enough that no flag is cut."""
    return subprocess.run(
        [sys.executable, "-c", "from hydo_cli.main import main; main()", *path, "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env={**os.environ, "COLUMNS": "250", "TERMINAL_WIDTH": "250", "NO_COLOR": "1"},
    )


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    commands = [line for line in README.splitlines() if "pytest" in line and line.startswith("pip install")]
    assert len(commands) == 1, commands
    assert commands[0] in ci.splitlines()


def test_readme_states_the_torch_pin_of_pyproject():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    pins = [d for d in deps if re.match(r"torch\b", d)]
    assert len(pins) == 1 and re.fullmatch(r"torch==\d+\.\d+\.\d+", pins[0]), pins
    version = pins[0].split("==")[1]
    assert f"`torch` is pinned to `{version}`" in README
    assert "never install an unpinned `torch`" in README


def test_readme_has_hydo_commands_for_every_subcommand():
    used = {path[0] for path, _ in HYDO if path}
    assert used == {"train", "eval", "export", "deploy", "plot", "sweep"}, used
    assert all(path for path, _ in HYDO), [p for p in HYDO if not p[0]]


@pytest.mark.parametrize("path", sorted({path for path, _ in HYDO}), ids=" ".join)
def test_readme_hydo_options_exist(path):
    r = hydo_help(path)
    assert r.returncode == 0, r.stderr
    assert "Usage" in r.stdout
    flags = {tok.split("=")[0] for p, rest in HYDO if p == path for tok in rest if tok.startswith("--")}
    missing = [f for f in sorted(flags) if not re.search(rf"(?<![\w-]){re.escape(f)}(?![\w-])", r.stdout)]
    assert not missing, f"`hydo {' '.join(path)} --help` does not list {missing}"


def test_readme_files_exist():
    missing = []
    for tokens in bash_commands(README):
        if tokens[0] == "python" and len(tokens) > 1 and tokens[1].endswith(".py"):
            if not (ROOT / tokens[1]).is_file():
                missing.append(tokens[1])
        for prev, tok in zip(["", *tokens], tokens, strict=False):
            if prev in OUTPUT_OPTIONS or not tok.startswith(REPO_DIRS):
                continue
            if not glob.glob(str(ROOT / tok)):
                missing.append(tok)
    assert not missing, missing


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


@pytest.mark.parametrize("page", ["README.md", "models/README.md", "docs/results.md", "docs/experiments.md"])
def test_links_resolve(page):
    text = (ROOT / page).read_text()
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue  # external
        file, _, anchor = target.partition("#")
        path = (ROOT / page).parent / file if file else ROOT / page
        if not path.exists():
            broken.append(target)
        elif anchor:
            headings = re.findall(r"^#+ (.+)$", path.read_text(), re.M)
            if anchor not in {github_anchor(h) for h in headings}:
                broken.append(target)
    assert not broken, broken


def test_gymnasium_lines_make_the_env():
    """The README's Gymnasium block, run as written: it makes a 6D-goal env that resets and steps."""
    blocks = re.findall(r"^```python\n(.*?)^```", README, re.S | re.M)
    gym_blocks = [b for b in blocks if "gymnasium.make" in b]
    assert len(gym_blocks) == 1 and len(gym_blocks[0].strip().splitlines()) == 2, gym_blocks
    scope: dict = {}
    exec(gym_blocks[0], scope)  # noqa: S102 - the README's own two lines
    env = scope["env"]
    obs, _ = env.reset(seed=0)
    assert env.unwrapped.goal_mode == "6d" and obs["points"].shape[1] == 3
    env.close()
