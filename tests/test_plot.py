"""Pictures: ``hydo plot`` (learning curves) and ``hydo eval --compare --plot`` (Table I) write images
that open, have a sensible size and are not blank; bad input is one line."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from hydo_cli.main import app
from tests.test_cli import hydo

pytest.importorskip("matplotlib")  # the plot extra (part of the test extra)
runner = CliRunner()


def assert_picture(path, min_w=400, min_h=250):
    """The file is a readable image of at least ``min_w`` x ``min_h`` pixels with more than one colour."""
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    h, w = img.shape[:2]
    assert w >= min_w and h >= min_h, (w, h)
    rgb = img[..., :3].reshape(-1, 3)
    assert rgb.std() > 0 and len(np.unique(rgb, axis=0)) > 1
    assert not list(path.parent.glob(f".{path.name}.*.tmp"))  # written atomically: no temp file left
    return img


def fake_run(folder, algo, seed, success, minutes_per_eval=1.0):
    """A training run folder as ``hydo train`` leaves it: config.json and eval.jsonl (one row per eval)."""
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"algo": algo, "seed": seed, "goals": "planar"}))
    rows = [
        {
            "env_steps": 1000 * (k + 1),
            "updates": 400 * (k + 1),
            "wall_s": 60.0 * minutes_per_eval * (k + 1),
            "success_rate": s,
            "mean_return": -1.0 + s,
            "episodes": 20,
        }
        for k, s in enumerate(success)
    ]
    (folder / "eval.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return folder


def test_plot_learning_curves_groups_seeds_by_method(tmp_path):
    runs = [
        fake_run(tmp_path / "hydo-cm-s0", "hydo-cm", 0, [0.1, 0.5, 0.8]),
        fake_run(tmp_path / "hydo-cm-s1", "hydo-cm", 1, [0.3, 0.7, 0.9], minutes_per_eval=1.5),
        fake_run(tmp_path / "hacman-s0", "hacman", 0, [0.0, 0.2, 0.4]),
        fake_run(tmp_path / "hacman-s1", "hacman", 1, [0.2, 0.4, 0.6]),
    ]
    out, js = tmp_path / "pics" / "curves.png", tmp_path / "curves.json"
    r = hydo("plot", *map(str, runs), "--out", str(out), "--json", str(js), "--heuristic", "0.54")
    assert r.returncode == 0, r.stderr
    assert_picture(out, min_w=800, min_h=300)
    data = json.loads(js.read_text())
    assert data["heuristic"] == 0.54
    assert list(data["methods"]) == ["hacman", "hydo-cm"]  # Table I's row order
    cm = data["methods"]["hydo-cm"]
    assert cm["name"] == "HyDo + CM" and len(cm["runs"]) == 2
    at_2000 = next(p for p in cm["vs_env_steps"] if p["env_steps"] == 2000)
    assert at_2000["success_mean"] == pytest.approx(0.6)
    assert (at_2000["success_min"], at_2000["success_max"]) == (0.5, 0.7)
    # vs minutes: at the end every seed's last evaluation counts; before seed 1's first, only seed 0's
    last = cm["vs_minutes"][-1]
    assert last["minutes"] == pytest.approx(4.5) and last["success_mean"] == pytest.approx(0.85)
    assert cm["vs_minutes"][0]["seeds"] == 1


@pytest.mark.parametrize(
    "args, message",
    [
        (["{tmp}/nothing-here"], "is not a folder"),
        (["{run}", "--heuristic", "1.5"], "--heuristic is a success rate"),
        (["{run}", "--out", "{tmp}/curves.gif"], "give a .png"),
        (["{run}", "--out", "{tmp}"], "is a folder"),
        (["{tmp}/empty"], "has no config.json"),
    ],
)
def test_plot_bad_input_is_one_line(tmp_path, args, message):
    run = fake_run(tmp_path / "run", "hydo", 0, [0.5])
    (tmp_path / "empty").mkdir()
    args = [a.format(tmp=tmp_path, run=run) for a in args]
    r = hydo("plot", *args)
    assert r.returncode != 0 and message in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_eval_compare_plot_draws_table_one(tmp_path):
    png = tmp_path / "table1.png"
    r = runner.invoke(
        app, ["eval", "random", "heuristic", "--compare", "--episodes", "2", "--plot", str(png)]
    )
    assert r.exit_code == 0, r.output
    img = assert_picture(png, min_w=500, min_h=300)
    assert img.shape[1] > img.shape[0]  # three groups of bars side by side


def test_table_one_figure_has_a_bar_and_whisker_per_method_and_split():
    from hydo_cli.figures import table1_figure

    def est(iqm):
        return {"iqm": iqm, "ci_low": iqm - 0.1, "ci_high": iqm + 0.05}

    splits = ["unseen-category", "unseen-instance", "train"]
    report = {
        "splits": splits,
        "goals": "planar",
        "episodes": 50,
        "aggregate": {
            "methods": {
                m: {"name": m, "targets": ["a", "b"], "splits": {s: est(0.2 + 0.1 * k) for s in splits}}
                for k, m in enumerate(["HyDo + CM", "HACMan", "heuristic"])
            }
        },
    }
    ax = table1_figure(report).axes[0]
    heights = sorted(round(p.get_height(), 3) for p in ax.patches)
    assert heights == [0.2] * 3 + [0.3] * 3 + [0.4] * 3
    assert [t.get_text() for t in ax.get_xticklabels()] == [
        "Unseen Category",
        "Unseen Instance",
        "Training Objects",
    ]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--plot", "{tmp}/t1.png"], "--plot draws Table I: add --compare"),
        (["--compare", "--plot", "{tmp}/t1.bmp"], "give a .png"),
        (["--compare", "--plot", "{tmp}/afile/t1.png"], "is a file, not a folder"),
    ],
)
def test_eval_plot_path_is_checked_before_any_episode(tmp_path, args, message):
    (tmp_path / "afile").write_text("x")
    r = hydo("eval", "random", "--episodes", "500", *[a.format(tmp=tmp_path) for a in args])
    assert r.returncode != 0 and message in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A real deploy session: one episode of the shipped model on the MuJoCo twin."""
    from tests.test_cli import MODEL

    folder = tmp_path_factory.mktemp("deploy") / "session"
    r = hydo(
        "deploy", "--robot", "sim", "--model", MODEL, "--episodes", "1", "--seed", "0", "--log", str(folder)
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return folder


def test_deploy_review_draws_a_row_per_step(session, tmp_path):
    steps = sorted((session / "steps").glob("e*-s*.npz"))
    png = tmp_path / "session.png"
    r = hydo("deploy", "review", str(session), "--out", str(png))
    assert r.returncode == 0, r.stderr
    img = assert_picture(png, min_w=900, min_h=250 * len(steps))
    assert f"{len(steps)} steps" in r.stderr
    # the contact star (lime) and the mask overlay (red) are drawn
    rgb = (img[..., :3] * 255).astype(int) if img.dtype != np.uint8 else img[..., :3].astype(int)
    assert ((rgb[..., 1] > 200) & (rgb[..., 0] < 80) & (rgb[..., 2] < 80)).any(), "no contact marker"
    assert ((rgb[..., 0] > 180) & (rgb[..., 1] < 90) & (rgb[..., 2] < 90)).any(), "no mask overlay"


def test_deploy_review_as_video(session, tmp_path):
    import cv2

    mp4 = tmp_path / "session.mp4"
    r = hydo("deploy", "review", str(session), "--out", str(mp4), "--max-steps", "2")
    assert r.returncode == 0, r.stderr
    cap = cv2.VideoCapture(str(mp4))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    assert len(frames) == 2 and frames[0].shape[1] >= 900 and frames[0].std() > 0


def test_deploy_review_finds_the_episode_in_a_ladder_rung_split_into_sessions(session, tmp_path):
    """A ladder rung run by two processes is a folder of sessions (``twin/e000-049``, ...): review
    draws the one that played ``--episode``, and without it says which sessions there are."""
    import shutil

    rung = tmp_path / "twin"
    for piece in ("e000-000", "e001-001"):
        shutil.copytree(session, rung / piece)
    r = hydo("deploy", "review", str(rung), "--episode", "0", "--out", str(tmp_path / "s.png"))
    assert r.returncode == 0 and (tmp_path / "s.png").is_file(), r.stderr
    r = hydo("deploy", "review", str(rung), "--out", str(tmp_path / "t.png"))
    assert r.returncode == 1 and "holds 2 sessions (e000-000, e001-001)" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["{tmp}"], "is not a deploy session folder"),
        (["{tmp}/none"], "is not a folder"),
        (["{session}", "--episode", "7"], "has no recorded steps of episode 7"),
        (["{session}", "--out", "{tmp}/s.gif"], "give a .png"),
    ],
)
def test_deploy_review_bad_input_is_one_line(session, tmp_path, args, message):
    r = hydo("deploy", "review", *[a.format(tmp=tmp_path, session=session) for a in args])
    assert r.returncode != 0 and message in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
