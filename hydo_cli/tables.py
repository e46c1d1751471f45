"""Rendering a ``hydo eval`` report: console tables (rich) and Markdown."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.table import Table

from hydo_cli.report import METHOD_NAMES, SPLIT_TITLES


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.1%}"


def run_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the per-run table (shared by the console and Markdown)."""
    compare, task = report["compare"], report["task"]
    header = ["run", "method"] + (["objects"] if compare else [])
    header += ["success", "steps to success", "left bin", "timeout", "refused", "refused prims", "idle prims"]
    flips = any("flip" in r.get("by_goal", {}) for r in report["runs"])
    header += (["entropy", "behaviours"] if task else []) + (["move", "flip"] if flips else [])
    header += ["policy", "ep/s"]
    rows = []
    for r in report["runs"]:
        f = r["failures"]
        steps = r["mean_steps_to_success"]
        run = r["target"] + (f" (recorded in {r['recorded']})" if "recorded" in r else "")
        row = [run, METHOD_NAMES.get(r["method"], r["method"])] + ([r["objects"]] if compare else [])
        row += [
            f"{r['success_rate']:.1%} ({round(r['success_rate'] * r['episodes'])}/{r['episodes']})",
            "-" if steps is None else f"{steps:.2f}",
            str(f["object_left_bin"]),
            str(f["timeout"]),
            str(f["primitive_rejected"]),
            str(r["rejected_primitives"]),
            "-" if "idle_share" not in r else f"{r['idle_share']:.0%}",  # records from before it have none
        ]
        if task:
            row += [
                f"{r['behaviour_entropy']:.3f}",
                f"{r['behaviours_seen']}/{report['task']['n_behaviours']}",
            ]
        if flips:  # 6D goals: success where the goal keeps the face up, and where it asks for a flip
            kinds = r.get("by_goal", {})
            row += [_pct(kinds[k]["success_rate"]) if k in kinds else "-" for k in ("move", "flip")]
        row += ["stochastic" if r["stochastic"] else "deterministic", f"{r['episodes_per_s']:.1f}"]
        rows.append(row)
    return header, rows


def compare_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    """Table I: method x split, each cell IQM [95% CI] of the success rate across that method's runs."""
    task = report["task"]
    splits = report["splits"]
    if task:
        header = ["Method", "Success", "Behaviour entropy", "Runs"]
    else:
        header = ["Method"] + [SPLIT_TITLES.get(s, s) for s in splits] + ["Runs"]
    rows = []
    for m in report["aggregate"]["methods"].values():
        cells = [cell(m["splits"][s]) for s in splits]
        if task:
            cells.append(cell(m["behaviour_entropy"]))
        rows.append([m["name"], *cells, str(len(m["targets"]))])
    return header, rows


def cell(e: dict) -> str:
    """``0.760 [0.718, 0.802]`` from an ``Estimate.as_dict()`` (``stats.Estimate.cell``), with its
    ``; seeds [...]`` interval where it has one."""
    from hydo_cli.stats import format_cell

    return format_cell(e["iqm"], e["ci_low"], e["ci_high"], 3, e.get("seed_ci_low"), e.get("seed_ci_high"))


def _budget(run: dict) -> dict | None:
    """A run's ``training`` (``hydo_cli.policies.training_budget``) where it is well formed: a record
    is a file from elsewhere, and records made before the key existed have none."""
    b = run.get("training")
    numbers = ("env_steps", "updates", "sample_gradients", "minutes", "max_minutes")
    if not isinstance(b, dict) or not all(isinstance(b.get(k), int | float) for k in numbers):
        return None
    learner = b.get("learner")
    if not isinstance(learner, dict) or not all(isinstance(v, int | float) for v in learner.values()):
        return None
    return b


#: how ``learner_text`` names a budget's learner settings, in this order
LEARNER_NAMES = {
    "denoise_steps": "K",
    "batch_size": "batch",
    "updates_per_step": "UTD",
    "policy_delay": "actor every",
}


def learner_text(learner: dict) -> str:
    """``K 5, batch 64, UTD 0.5, actor every 2`` from a budget's ``learner``."""
    keys = [k for k in LEARNER_NAMES if k in learner] + sorted(k for k in learner if k not in LEARNER_NAMES)
    return ", ".join(f"{LEARNER_NAMES.get(k, k)} {learner[k]:g}" for k in keys)


def budget_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    """One row per trained run (not per split) with its training budget; no rows when no run has one
    (baselines, exported models, records made before runs carried it)."""
    header = ["run", "method", "minutes", "env steps", "updates", "sample-gradients", "learner"]
    rows, seen = [], set()
    for r in report["runs"]:
        b = _budget(r)
        if b is None or r["target"] in seen:
            continue
        seen.add(r["target"])
        limit = f" of {b['max_minutes']:g}" if b["max_minutes"] else ""
        rows.append(
            [
                r["target"],
                METHOD_NAMES.get(r["method"], r["method"]),
                f"{b['minutes']:.0f}{limit}",
                f"{b['env_steps']:,}",
                f"{b['updates']:,}",
                f"{b['sample_gradients'] / 1e6:.1f}M",
                learner_text(b["learner"]),
            ]
        )
    return header, rows


def learner_notes(report: dict) -> list[str]:
    """One line per method whose runs were trained with different learner settings: a Table I row
    should be one setting's seeds."""
    by_method: dict[str, dict[str, list[str]]] = {}
    for r in report["runs"]:
        b = _budget(r)
        if b is not None:
            targets = by_method.setdefault(r["method"], {}).setdefault(learner_text(b["learner"]), [])
            if r["target"] not in targets:
                targets.append(r["target"])
    return [
        f"note: {METHOD_NAMES.get(m, m)}'s runs were trained with {len(v)} different learners: "
        + "; ".join(f"{text} ({', '.join(ts)})" for text, ts in v.items())
        for m, v in by_method.items()
        if len(v) > 1
    ]


def object_rows(report: dict, split: str) -> tuple[list[str], list[list[str]]]:
    runs = [r for r in report["runs"] if r["objects"] == split]
    objects = sorted({o for r in runs for o in r["per_object"]})
    header = ["object"] + [r["target"] for r in runs]
    rows = []
    for o in objects:
        cells = []
        for r in runs:
            p = r["per_object"].get(o)
            cell = "-" if p is None else f"{p['success_rate']:.0%} ({p['episodes']})"
            if p is not None and p.get("flip_episodes"):  # 6D goals: the object's flips on their own
                cell += f", flips {p['flip_success_rate']:.0%} ({p['flip_episodes']})"
            cells.append(cell)
        rows.append([o, *cells])
    return header, rows


def rich_table(title: str, header: list[str], rows: list[list[str]]) -> Table:
    table = Table(title=title, title_justify="left")
    for h in header:
        table.add_column(h)
    for row in rows:
        table.add_row(*row)
    return table


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    def esc(c: str) -> str:
        return str(c).replace("|", "\\|")

    lines = ["| " + " | ".join(esc(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def setup_line(report: dict) -> str:
    if report["task"]:
        where = f"task {report['task']['name']} (fixed start, |B| = {report['task']['n_behaviours']})"
    else:
        where = f"objects {', '.join(report['splits'])}, {report['goals']} goals, clutter {report['clutter']}"
    return (
        f"{where}; {report['obs']} observations; {report['episodes']} episodes per run and split; "
        f"seed {report['seed']}"
    )


def markdown_report(report: dict) -> str:
    """The whole report as Markdown: setup, Table I (--compare), runs, IQM, per-object success."""
    agg = report["aggregate"]
    out = ["# hydo eval", "", f"`{report['command']}`", "", setup_line(report) + ".", ""]
    if report["compare"]:
        title = "Behaviour diversity" if report["task"] else "Table I: success rate"
        out += [f"## {title}, IQM [95% CI] across runs", "", markdown_table(*compare_rows(report)), ""]
        for m in agg["methods"].values():
            line = f"- {m['name']} ({', '.join(m['targets'])}): {next(iter(m['splits'].values()))['note']}"
            if report["task"]:
                line += f"; behaviour entropy: {m['behaviour_entropy']['note'].split('; ', 1)[-1]}"
            out.append(line + ".")
        out.append("")
    out += ["## Runs", "", markdown_table(*run_rows(report)), ""]
    header, rows = budget_rows(report)
    if rows:
        out += ["## Training budgets", "", markdown_table(header, rows), *learner_notes(report), ""]
    out += ["## IQM across runs, per method", ""]
    for m in agg["methods"].values():
        out.append(f"- {m['name']}: success rate IQM {cell(m['all'])}: {m['all']['note']}.")
        if report["task"]:
            out.append(f"- {m['name']}: behaviour entropy IQM {cell(m['behaviour_entropy'])}.")
    out.append("")
    for split in report["splits"]:
        header, rows = object_rows(report, split)
        if len(rows) > 1:
            out += [f"## Success per object: {split}", "", markdown_table(header, rows), ""]
    out += [
        "Columns: `left bin` / `timeout` count failed episodes by how they ended; `refused` counts failed "
        "episodes with at least one refused primitive (also counted under their end reason); "
        "`refused prims` counts refused primitives in all episodes. Statistics: `hydo_cli/stats.py`; "
        "behaviour descriptors: `sim/tasks.py`.",
        "",
    ]
    return "\n".join(out)


def print_report(report: dict) -> None:
    out = Console() if sys.stdout.isatty() else Console(width=160)  # logs and pipes: no 80-column wrap
    out.print(rich_table(f"hydo eval: {setup_line(report)}", *run_rows(report)))
    agg = report["aggregate"]
    if report["compare"]:
        title = "Behaviour diversity" if report["task"] else "Table I: success rate"
        out.print(rich_table(f"{title}, IQM [95% CI] across runs", *compare_rows(report)))
        header, rows = budget_rows(report)
        if rows:  # "at the same budget": what each trained run was given and did
            out.print(rich_table("training budgets", header, rows))
        for line in learner_notes(report):
            out.print(line, highlight=False)
    else:
        for split in report["splits"]:
            header, rows = object_rows(report, split)
            if 1 < len(rows) <= 60:
                out.print(rich_table(f"success per object ({split})", header, rows))
    for m in agg["methods"].values():  # never pooled across methods
        a = m["all"]
        out.print(
            f"{m['name']}: success rate IQM across its runs: [bold]{cell(a)}[/]  ({a['note']})",
            highlight=False,
        )
        if report["task"]:
            e = m["behaviour_entropy"]
            out.print(
                f"{m['name']}: behaviour entropy IQM across its runs: [bold]{cell(e)}[/]", highlight=False
            )
