"""The benchmarks' report: one results page from every sweep under ``benchmarks/results/``, and its summary table in
the README, the algorithm's page and the benchmarks README.

    python benchmarks/report.py            # write docs/results.md, the learning curves and the three marked blocks
    python benchmarks/report.py --check    # exit 1 if the page or a marked block is not what the results give
    python benchmarks/report.py benchmarks/results/doorkey8x8     # one sweep, while it runs: its benchmark.md

Each sweep's folder ``benchmarks/results/<name>/`` (written by ``python -m benchmarks.run``) holds ``results.csv``,
``curves/<run>.csv``, ``runs/<run>.json`` and the JSON files of ``benchmarks/evaluate.py``. The page
(:data:`PAGE`, ``docs/results.md``) has the summary of where each task stands (:data:`SUMMARY`: HhP and the flat
baselines, with seeds, steps and labels), then one section per sweep: the command that reproduces it, the commits
its runs were trained at, one row per env x variant (mean ± std over seeds of the success rate of the deterministic
and of the stochastic policy on the fresh evaluation episodes, of the labels used and of the wall time) and one
learning-curve plot per env (``curves_<env>.png`` in the sweep's folder: success rate at the periodic evaluations
against env steps, mean over seeds, a band of ± one std, a line per variant). The summary table is copied between
the markers ``<!-- results:begin -->`` / ``<!-- results:end -->`` of ``README.md`` and ``benchmarks/README.md``
and ``.. results:begin`` / ``.. results:end`` of ``docs/modules/hhp.rst`` (:data:`BLOCKS`), so the three agree.

Given sweep folders (or their ``results.csv``), it writes ``benchmark.md`` and the plots next to each instead, and
lists runs started but without a row yet (still training, or stopped) with the steps their periodic evaluations
reached, drawn as dashed lines (``curves/<run>.partial.csv``): a sweep of runs that take hours can be looked at while
it runs. Needs the ``plots`` extra (pandas, matplotlib).
"""

import argparse
import json
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np
import pandas as pd
import yaml

try:
    from benchmarks.run import Experiment, _curve_from_evaluations, attempt_evaluations
except ImportError:  # run as a script, python benchmarks/report.py: the repository's root is not on the path
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from benchmarks.run import Experiment, _curve_from_evaluations, attempt_evaluations

#: variant -> name in tables and legends, in the order of tables and plots
VARIANT_NAMES = {"hhp": "HhP", "dqn": "DQN", "ppo": "PPO", "ppo_rnd": "PPO + RND", "ddpg": "DDPG",
                 "ddpg_her": "DDPG + HER", "tqc_her": "TQC + HER"}
#: columns a results file must have
REQUIRED_COLUMNS = ("env", "variant", "seed", "steps", "success_det", "success_stoch", "labels_used", "wall_seconds")
#: points of the common step grid the seeds' curves are interpolated onto
CURVE_GRID_POINTS = 100


def variant_name(variant: str) -> str:
    """A variant's name in tables and legends; a sweep's own HhP variants read "HhP, <the rest>" (``hhp_rho0.2``:
    "HhP, rho0.2"; ``hhp_no_curiosity``: "HhP, no curiosity")."""
    if variant in VARIANT_NAMES:
        return VARIANT_NAMES[variant]
    return "HhP, " + variant[len("hhp_"):].replace("_", " ") if variant.startswith("hhp_") else variant


def _variant_order(variants: Sequence[str]) -> list[str]:
    known = [variant for variant in VARIANT_NAMES if variant in set(variants)]
    return known + sorted(set(variants) - set(known))


def read_results(csv_path: Path) -> pd.DataFrame:
    """A sweep's ``results.csv``, checked for the columns the report reads."""
    if not csv_path.is_file():
        raise SystemExit(f"No results file {csv_path}: run python -m benchmarks.run CONFIG first (or pass its results.csv)")
    results = pd.read_csv(csv_path)
    missing = [column for column in REQUIRED_COLUMNS if column not in results.columns]
    if missing:
        raise SystemExit(f"{csv_path} lacks the columns {', '.join(missing)}: not written by python -m benchmarks.run")
    return results


def _mean_std(values: pd.Series, digits: int = 2, scale: float = 1.0, thousands: bool = False) -> str:
    """``mean ± std`` (sample std over seeds; the mean alone for one seed; "–" when there is no value);
    ``thousands``: with a comma between thousands (steps)."""
    values = values.dropna().astype(float) / scale
    spec = f"{',' if thousands else ''}.{digits}f"
    if values.empty:
        return "–"
    if len(values) == 1:
        return f"{values.iloc[0]:{spec}}"
    return f"{values.mean():{spec}} ± {values.std(ddof=1):{spec}}"


def _time_unit(seconds: pd.Series) -> tuple[str, float]:
    longest = float(seconds.max()) if len(seconds.dropna()) else 0.0
    if longest < 600:
        return "s", 1.0
    if longest < 36_000:
        return "min", 60.0
    return "h", 3600.0


def run_summary(row: NamedTuple, folder: Path) -> Optional[dict]:
    """A results row's run summary (``runs/<run>.json`` under ``folder``), None where it has none."""
    summary = getattr(row, "summary", None)
    path = folder / summary if isinstance(summary, str) else None
    return json.loads(path.read_text()) if path is not None and path.is_file() else None


def subgoal_counts(results: pd.DataFrame, folder: Path) -> pd.Series:
    """The sub-goals each HhP run had found at its end (``num_subgoals`` of its summary, ``runs/<run>.json``), by
    row; NaN for the baselines and for runs without a summary."""
    counts = [(run_summary(row, folder) or {}).get("num_subgoals", np.nan) for row in results.itertuples()]
    return pd.Series(counts, index=results.index, dtype=float)


def markdown_table(results: pd.DataFrame) -> str:
    """One row per env x variant: seeds, steps, success (deterministic, stochastic), labels used, sub-goals found
    (where ``results`` has a ``subgoals`` column with a value: :func:`subgoal_counts`), wall time.

    :param results: the rows of ``results.csv``
    :return: the table in Markdown (GitHub's pipe tables)
    """
    unit, scale = _time_unit(results["wall_seconds"])
    subgoals = "subgoals" in results and results["subgoals"].notna().any()
    header = [
        "env", "variant", "seeds", "steps", "success (deterministic)", "success (stochastic)", "labels used",
        *(["sub-goals"] if subgoals else []), f"wall time ({unit})",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([" --- "] * 2 + [" ---: "] * (len(header) - 2)) + "|"]
    for env in sorted(results["env"].unique()):
        rows = results[results["env"] == env]
        for variant in _variant_order(list(rows["variant"].unique())):
            runs = rows[rows["variant"] == variant]
            steps = sorted(int(value) for value in runs["steps"].unique())
            cells = [
                env,
                variant_name(variant),
                str(runs["seed"].nunique()),
                " / ".join(f"{value:,}" for value in steps),
                _mean_std(runs["success_det"]),
                _mean_std(runs["success_stoch"]),
                _mean_std(runs["labels_used"], digits=0),
                *([_mean_std(runs["subgoals"], digits=0)] if subgoals else []),
                _mean_std(runs["wall_seconds"], digits=1 if unit != "s" else 0, scale=scale),
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def mean_curve(curves: Sequence[pd.DataFrame], column: str = "success") -> Optional[pd.DataFrame]:
    """The seeds' curves on one step grid (linear interpolation, within the steps every seed covers): mean, std.

    :param curves: one DataFrame per seed, with ``steps`` and ``column``
    :param column: the value to average
    :return: ``steps``, ``mean``, ``std`` (0 for a single seed), or None without points
    """
    curves = [curve.sort_values("steps") for curve in curves if len(curve)]
    if not curves:
        return None
    if len(curves) == 1:
        curve = curves[0]
        return pd.DataFrame({"steps": curve["steps"], "mean": curve[column], "std": 0.0})
    low = max(float(curve["steps"].iloc[0]) for curve in curves)
    high = min(float(curve["steps"].iloc[-1]) for curve in curves)
    if high < low:
        return None
    grid = np.linspace(low, high, CURVE_GRID_POINTS) if high > low else np.array([low])
    values = np.stack([np.interp(grid, curve["steps"], curve[column]) for curve in curves])
    return pd.DataFrame({"steps": grid, "mean": values.mean(axis=0), "std": values.std(axis=0, ddof=1)})


#: the baseline whose final success the other variants' periodic evaluations are timed against, and the most that
#: level may be (the Fetch target "faster than HER": DDPG + HER's final success or 0.5, whichever is lower)
REACH_BASELINE, REACH_CAP = "ddpg_her", 0.5


def first_reach(curve: pd.DataFrame, level: float) -> Optional[float]:
    """The first step of a run's periodic evaluations (``steps``, ``success``) whose success is at least ``level``;
    None where none is."""
    reached = curve.sort_values("steps").loc[lambda frame: frame["success"] >= level - 1e-9, "steps"]
    return float(reached.iloc[0]) if len(reached) else None


def steps_to_level(results: pd.DataFrame, folder: Path, baseline: str = REACH_BASELINE,
                   cap: float = REACH_CAP) -> Optional[str]:
    """For each env where ``baseline`` finished: the level min(its mean final deterministic success, ``cap``), and for
    each variant the steps at which each seed's periodic evaluations (``curves/<run>.csv``) first reach it, mean ±
    std over the seeds that did (how many of how many). None without such an env.

    :return: the table in Markdown
    """
    if "curve" not in results or baseline not in set(results["variant"]):
        return None
    lines = ["| env | level | variant | steps to the level | seeds that reached it |",
             "| --- | ---: | --- | ---: | ---: |"]
    for env in sorted(results["env"].unique()):
        rows = results[results["env"] == env]
        final = rows.loc[rows["variant"] == baseline, "success_det"]
        level = min(float(final.mean()), cap) if len(final) else 0.0
        if level <= 0.0:
            continue  # the baseline solved nothing: no level to time
        for variant in _variant_order(list(rows["variant"].unique())):
            runs = rows[(rows["variant"] == variant) & rows["curve"].notna()]
            steps = [first_reach(pd.read_csv(folder / path), level) for path in runs["curve"]
                     if (folder / path).is_file()]
            if not steps:
                continue
            reached = pd.Series([value for value in steps if value is not None], dtype=float)
            cells = [env, f"{level:.2f}", variant_name(variant), _mean_std(reached, digits=0, thousands=True),
                     f"{len(reached)} of {len(steps)}"]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n" if len(lines) > 2 else None


def unfinished_runs(results: pd.DataFrame, folder: Path) -> pd.DataFrame:
    """The runs with a log folder (``logs/<run>``) and no row in ``results``: still training, or stopped. The newest
    periodic evaluations under each log folder (every part of a resumed run) become ``curves/<run>.partial.csv``; a
    finished run's partial curve, written while it ran, is removed (its row's curve replaces it).

    :return: one row per run: ``env`` (as in run names: ``/`` written ``-``), ``variant``, ``seed``, ``steps`` (the
        last periodic evaluation's, 0 before any), ``success`` (at that evaluation), ``curve`` (relative to ``folder``)
    """
    finished = {Experiment(row.env, row.variant, int(row.seed), int(row.steps)).name for row in results.itertuples()}
    rows = []
    for log in sorted((folder / "logs").glob("*__*__s*")):
        if not log.is_dir():
            continue
        relative = Path("curves") / f"{log.name}.partial.csv"
        if log.name in finished:
            (folder / relative).unlink(missing_ok=True)
            continue
        env, variant, seed = log.name.rsplit("__", 2)
        written = _curve_from_evaluations(attempt_evaluations(log), folder / relative)
        curve = pd.read_csv(folder / relative) if written else None
        rows.append({"env": env, "variant": variant, "seed": int(seed[1:]),
                     "steps": int(curve["steps"].iloc[-1]) if curve is not None else 0,
                     "success": float(curve["success"].iloc[-1]) if curve is not None else float("nan"),
                     "curve": str(relative) if written else None})
    return pd.DataFrame(rows, columns=["env", "variant", "seed", "steps", "success", "curve"])


def unfinished_table(unfinished: pd.DataFrame) -> str:
    """The unfinished runs in Markdown (empty without any)."""
    if unfinished.empty:
        return ""
    lines = ["| run | steps reached | success at the last periodic evaluation |", "| --- | ---: | ---: |"]
    for row in unfinished.itertuples():
        success = "–" if np.isnan(row.success) else f"{row.success:.2f}"
        lines.append(f"| {row.env} {variant_name(row.variant)} seed {row.seed} | {row.steps:,} | {success} |")
    return "\n".join(lines) + "\n"


def plot_curves(results: pd.DataFrame, folder: Path, unfinished: Optional[pd.DataFrame] = None) -> list[Path]:
    """One plot per env with learning curves: success rate against env steps, mean ± std over seeds per variant;
    each unfinished run (:func:`unfinished_runs`) a dashed line of its own.

    :param results: the rows of ``results.csv`` (``curve``: a path relative to ``folder``, or empty)
    :param folder: the folder of ``results.csv``, where the plots go
    :param unfinished: runs without a row yet, with their partial curves
    :return: the plots written
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    if "curve" not in results.columns:
        return written
    unfinished = unfinished if unfinished is not None else pd.DataFrame(columns=["env", "variant", "seed", "steps", "curve"])
    unfinished = unfinished[unfinished["curve"].notna()]
    # envs by their names in run names ('/' written '-'), titled with their ids where a finished run gives one
    titles = {env.replace("/", "-"): env for env in results["env"].unique()}
    titles.update({env: titles.get(env, env) for env in unfinished["env"].unique()})
    for name in sorted(titles):
        env = titles[name]
        rows = results[(results["env"] == env) & results["curve"].notna()]
        partial = unfinished[unfinished["env"] == name]
        if rows.empty and partial.empty:
            continue
        fig, ax = plt.subplots(figsize=(6, 4))
        for variant in _variant_order(list(rows["variant"].unique())):
            paths = [folder / path for path in rows[rows["variant"] == variant]["curve"]]
            curves = [pd.read_csv(path) for path in paths if path.is_file()]
            curve = mean_curve(curves)
            if curve is None:
                continue
            label = f"{variant_name(variant)} ({len(curves)} seed{'s' if len(curves) > 1 else ''})"
            (line,) = ax.plot(curve["steps"], curve["mean"], label=label)
            ax.fill_between(
                curve["steps"], (curve["mean"] - curve["std"]).clip(0, 1), (curve["mean"] + curve["std"]).clip(0, 1),
                color=line.get_color(), alpha=0.2, linewidth=0,
            )
        for row in partial.itertuples():
            curve = pd.read_csv(folder / row.curve)
            ax.plot(curve["steps"], curve["success"], linestyle="--", marker=".",
                    label=f"{variant_name(row.variant)} seed {row.seed} (unfinished, {row.steps:,} steps)")
        ax.set_title(env)
        ax.set_xlabel("env steps")
        ax.set_ylabel("success rate (periodic evaluations)")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = folder / f"curves_{env.replace('/', '-')}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    return written


def greedy_rows(results: pd.DataFrame, folder: Path, key: str = "break_cycles") -> list[tuple[int, str, str]]:
    """The HhP runs whose deterministic figure is plain greedy: their summary (``runs/<run>.json``) predates
    ``break_cycles`` or says it was off (``key="stochastic_breaks_cycles"``: whose stochastic figure is plain
    epsilon-greedy). Rows of other variants, or without a summary, are not named.

    :return: per such run: its row's index in ``results``, its name in the tables, its run name (its log folder's)
    """
    named = []
    for index, row in zip(results.index, results.itertuples(index=False)):
        summary = run_summary(row, folder) if str(row.variant).startswith("hhp") else None
        if summary is not None and not summary.get(key, False):
            run = Experiment(row.env, row.variant, int(row.seed), int(row.steps)).name
            named.append((index, f"{row.env} {variant_name(str(row.variant))} seed {int(row.seed)}", run))
    return named


def reevaluations(folder: Path) -> list[dict]:
    """The figures of models that ``benchmarks/evaluate.py`` evaluated again with cycles broken: the JSON files it wrote
    into ``folder`` (``{"env", "episodes", "runs": [...]}``, or the rows under ``"variants"``). A figure counts where
    its row records ``break_cycles`` true, or, in files written before rows recorded it, where no load option turned
    it off (models saved before ``break_cycles`` existed load with it on); files in order of name.

    :return: each figure's ``success`` (deterministic), ``episodes``, ``file`` (its name) and ``folders`` (those of its
        model's path: a run's log folder is named as the run)
    """
    found: list[dict] = []
    for path in sorted(folder.glob("*.json")):
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(data, dict):
            continue
        rows = data.get("runs")
        if rows is None and isinstance(data.get("variants"), dict):  # one list per variant
            rows = [row for variant in data["variants"].values() if isinstance(variant, list) for row in variant]
        for row in rows if isinstance(rows, list) else []:
            if not isinstance(row, dict) or "deterministic" not in row:
                continue
            options = row.get("load_options") or {}
            if not row.get("break_cycles", options.get("break_cycles", True)):
                continue
            found.append({"success": float(row["deterministic"]), "episodes": data.get("episodes"), "file": path.name,
                          "folders": set(Path(str(row.get("model", ""))).parts)})
    return found


def break_cycles_note(results: pd.DataFrame, folder: Path) -> tuple[pd.DataFrame, str]:
    """The rows with the deterministic figures of plain greedy HhP runs replaced by their :func:`reevaluations` on the
    same episodes (as many, the same seeds), and the note under the table that says which and what they were, and
    which runs' stochastic figures are plain epsilon-greedy."""
    greedy, epsilon_greedy = greedy_rows(results, folder), greedy_rows(results, folder, "stochastic_breaks_cycles")
    if not greedy and not epsilon_greedy:
        return results, ""
    again = reevaluations(folder)
    results = results.copy()
    replaced, kept = [], []
    for index, name, run in greedy:
        episodes = results.loc[index, "eval_episodes"] if "eval_episodes" in results else None
        same = [figure for figure in again if run in figure["folders"] and (
            episodes is None or pd.isna(episodes) or figure["episodes"] is None or int(figure["episodes"]) == int(episodes))]
        if not same:  # never evaluated again, or on other episodes than the runner's
            kept.append(name)
            continue
        figure = same[0]
        plain = float(results.loc[index, "success_det"])
        results.loc[index, "success_det"] = figure["success"]
        replaced.append(f"{name} ({figure['success']:.2f}; plain greedy {plain:.2f}; `{figure['file']}`)")
    note = "\nHhP's deterministic policy breaks its cycles (`break_cycles`, the default)."
    if replaced:
        note += (" These runs were evaluated plain greedy by the runner, before it existed, and again with it on the "
                 "same episodes by `benchmarks/evaluate.py`, whose figures the table shows: " + "; ".join(replaced) + ".")
    if kept:
        note += (" These runs were evaluated plain greedy only (their models not evaluated again), and the table shows "
                 "that: " + "; ".join(kept) + ".")
    if epsilon_greedy:
        note += (" The stochastic policy breaks its cycles too (epsilon-greedy around them); these runs' stochastic "
                 "figures are plain epsilon-greedy, evaluated before it did: "
                 + "; ".join(name for _, name, _ in epsilon_greedy) + ".")
    return results, note + "\n"


def report(csv_path: Path) -> tuple[str, Path, list[Path]]:
    """Write ``benchmark.md`` and the plots next to ``csv_path``.

    :return: the table, the Markdown file and the plots
    """
    if csv_path.is_file() or not (csv_path.parent / "logs").is_dir():
        results = read_results(csv_path)
    else:  # a sweep whose runs are all still training
        results = pd.DataFrame(columns=[*REQUIRED_COLUMNS, "curve", "eval_episodes"])
    results, cycles_note = break_cycles_note(results, csv_path.parent)
    table = markdown_table(results)
    episodes = sorted(int(value) for value in results["eval_episodes"].dropna().unique()) if "eval_episodes" in results else []
    note = (
        f"Mean ± std over seeds. Success: fraction of {' / '.join(map(str, episodes)) or 'the'} fresh evaluation "
        "episodes (seeds seed + 10000, ...) solved by the deterministic and by the stochastic policy. Labels: "
        "preference queries answered (HhP only). Wall time: training and evaluation of one run.\n"
    )
    note += cycles_note
    markdown = csv_path.parent / "benchmark.md"
    unfinished = unfinished_runs(results, csv_path.parent)
    plots = plot_curves(results, csv_path.parent, unfinished)
    figures = "".join(f"\n![{path.stem}]({path.name})\n" for path in plots)
    pending = unfinished_table(unfinished)
    if pending:
        pending = ("\nRuns without a final evaluation (still training or stopped; dashed in the plots, from their "
                   f"periodic evaluations):\n\n{pending}")
        table = table + pending
    markdown.write_text(f"# Results of {csv_path.parent.name}\n\n{table}\n{note}{figures}")
    return table, markdown, plots


# ---------------------------------------------------------------------- the results page and its summary

#: the repository's root
ROOT = Path(__file__).resolve().parent.parent
#: where the sweeps' folders are, relative to the root
RESULTS = Path("benchmarks/results")
#: the sweep files, relative to the root
EXPERIMENTS = Path("benchmarks/experiments")
#: the results page, relative to the root
PAGE = Path("docs/results.md")
#: the files with a marked summary block, relative to the root: path -> markup ("md" or "rst")
BLOCKS = {Path("README.md"): "md", Path("docs/modules/hhp.rst"): "rst", Path("benchmarks/README.md"): "md"}
MARKERS = {"md": ("<!-- results:begin -->", "<!-- results:end -->"), "rst": (".. results:begin", ".. results:end")}
#: the success rate a task's target asks of every seed, deterministic and stochastic
TARGET = 0.9


class Source(NamedTuple):
    """Where a row of the summary comes from: a sweep's folder (under :data:`RESULTS`) and one of its variants."""

    sweep: str
    variant: str


class Task(NamedTuple):
    """A row group of the summary: an env, HhP's row (the settings users train it with), the flat baselines' rows
    (a baseline its sweep file names and that has no row yet: "not run yet"); ``hhp`` None: not run yet."""

    env: str
    hhp: Optional[Source]
    baselines: tuple[Source, ...] = ()
    note: str = ""
    not_run: tuple[str, ...] = ()  # variants (of VARIANT_NAMES) not run on this task yet
    former: Optional[Source] = None  # HhP with the task's own settings, before one entry served every MiniGrid task


#: the method of a task's :attr:`Task.former` row
FORMER = "HhP, the task's former own entry"
#: the ``minigrid`` entry before its sub-goal learners took the class's reward and horizon (alpha 0.5, discount 0.9,
#: 50-step tries) in place of alpha 0 with clipped TD targets, discount 0.99 and 100-step tries (minigrid_entry.yml)
CLIPPED = Source("minigrid_entry", "hhp_clipped_learners")
#: where each task stands: HhP as ``sb3_hhp/hyperparams/hhp.yml`` trains it on that env, and the flat baselines
SUMMARY = (
    Task("MiniGrid-DoorKey-8x8-v0", Source("minigrid_entry", "hhp"),
         (CLIPPED, Source("doorkey8x8", "dqn"), Source("doorkey8x8", "ppo"), Source("doorkey8x8", "ppo_rnd")),
         former=Source("doorkey8x8_entry", "hhp")),
    Task("MiniGrid-KeyCorridorS4R3-v0", Source("minigrid_entry", "hhp"),
         (CLIPPED, Source("minigrid_tasks", "ppo"), Source("minigrid_tasks", "ppo_rnd")),
         former=Source("minigrid_tasks", "hhp_one_hot_new_open")),
    Task("MiniGrid-MultiRoom-N12-S10-v0", Source("minigrid_entry", "hhp"),
         (CLIPPED, Source("minigrid_tasks", "ppo"), Source("minigrid_tasks", "ppo_rnd")),
         former=Source("minigrid_tasks", "hhp_rerun")),
    Task("MiniGrid-DoorKey-16x16-v0", Source("minigrid_entry", "hhp"),
         (CLIPPED, Source("minigrid_tasks", "ppo"), Source("minigrid_tasks", "ppo_rnd"))),
    Task("MiniGrid-ObstructedMaze-1Q-v1", Source("minigrid_entry", "hhp"),
         (Source("minigrid_tasks", "ppo"), Source("minigrid_tasks", "ppo_rnd")),
         former=Source("minigrid_tasks", "hhp")),
    Task("FetchReach-v4", Source("fetch_reach", "hhp"), (Source("fetch_reach", "ddpg_her"), Source("fetch_reach", "tqc_her"))),
    Task("Fetch Push, PickAndPlace, Slide (the `fetch` entry)", None, note="not run yet"),
    Task("Atari (Montezuma's Revenge, Pitfall, ...; the `atari` entry)", None, note="not run yet"),
)
SUMMARY_HEADER = ("task", "method", "sweep: variant", "steps", "seeds", "success (deterministic)",
                  "success (stochastic)", "labels", f">= {TARGET} on every seed")


def _seeds(seeds: Sequence[int]) -> str:
    """``0-2``, ``0-2, 5``: the seeds in runs of consecutive ones."""
    seeds, runs = sorted(set(int(seed) for seed in seeds)), []
    for seed in seeds:
        if runs and seed == runs[-1][1] + 1:
            runs[-1][1] = seed
        else:
            runs.append([seed, seed])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def _steps(runs: pd.DataFrame) -> str:
    return " / ".join(f"{value:,}" for value in sorted(int(value) for value in runs["steps"].unique()))


def sweep_results(folder: Path) -> pd.DataFrame:
    """A sweep's rows as its tables show them (:func:`break_cycles_note`'s figures)."""
    return break_cycles_note(read_results(folder / "results.csv"), folder)[0]


def summary_rows(root: Path = ROOT) -> list[list[str]]:
    """The summary's rows (:data:`SUMMARY`), cells as :data:`SUMMARY_HEADER`, from the sweeps' results files."""
    cache: dict[str, pd.DataFrame] = {}
    planned = {(name, variant) for name, files in sweep_files(root).items() for _, data in files
               for variant in data.get("variants") or []}
    rows = []
    for task in SUMMARY:
        if task.hhp is None:
            rows.append([task.env, "HhP", "–", "–", "–", task.note, task.note, "–", "–"])
            continue
        sources = [(task.hhp, "HhP")] + ([(task.former, FORMER)] if task.former is not None else [])
        sources += [(source, variant_name(source.variant)) for source in task.baselines]
        for index, (source, method) in enumerate(sources):
            if source.sweep not in cache:
                folder = root / RESULTS / source.sweep
                cache[source.sweep] = (sweep_results(folder) if (folder / "results.csv").is_file()
                                       else pd.DataFrame(columns=list(REQUIRED_COLUMNS)))
            results = cache[source.sweep]
            runs = results[(results["env"] == task.env) & (results["variant"] == source.variant)]
            if runs.empty and (source.sweep, source.variant) in planned:
                rows.append([task.env if index == 0 else "", method, f"`{source.sweep}`: `{source.variant}`", "–", "–",
                             "not run yet", "not run yet", "–", "–"])
                continue
            if runs.empty:
                raise SystemExit(f"{RESULTS / source.sweep / 'results.csv'} has no {task.env} {source.variant} row: "
                                 "change report.SUMMARY or run that sweep")
            met = ["yes" if (runs[column].astype(float) >= TARGET).all() else "no"
                   for column in ("success_det", "success_stoch")]
            rows.append([
                task.env if index == 0 else "", method,
                f"`{source.sweep}`: `{source.variant}`", _steps(runs), _seeds(runs["seed"]),
                _mean_std(runs["success_det"]), _mean_std(runs["success_stoch"]),
                _mean_std(runs["labels_used"], digits=0), " / ".join(met),
            ])
        rows += [["", VARIANT_NAMES[variant], "–", "–", "–", "not run yet", "not run yet", "–", "–"]
                 for variant in task.not_run]
    return rows


SUMMARY_NOTE = (
    "Mean ± std over the seeds named, each seed's figure the success rate on 100 fresh evaluation episodes (seeds "
    "seed + 10000, ...), deterministic and stochastic policy; labels: preference questions answered (HhP only); "
    "steps: primitive env steps of training. HhP: the settings of its env's entry in `sb3_hhp/hyperparams/hhp.yml`, "
    "scripted oracle. Generated by `python benchmarks/report.py` from `benchmarks/results/`; every sweep, its "
    "command and its learning curves: `docs/results.md`."
)


def markdown_summary(rows: list[list[str]]) -> str:
    """The summary as a Markdown pipe table and its note."""
    lines = ["| " + " | ".join(SUMMARY_HEADER) + " |", "| --- | --- | --- |" + " ---: |" * 5 + " --- |"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n\n" + SUMMARY_NOTE + "\n"


def rst_summary(rows: list[list[str]]) -> str:
    """The summary as an reStructuredText list-table and its note (the same cells)."""
    lines = [".. list-table::", "   :header-rows: 1", ""]
    for row in [list(SUMMARY_HEADER), *rows]:
        cells = [cell.replace("`", "``").replace("````", "") or r"\ " for cell in row]
        lines.append("   * - " + cells[0])
        lines += [f"     - {cell}" for cell in cells[1:]]
    return "\n".join(lines) + "\n\n" + SUMMARY_NOTE.replace("`", "``") + "\n"


def sweep_files(root: Path = ROOT) -> dict[str, list[tuple[Path, dict]]]:
    """The sweep files, by the folder they write into (their ``name``, default their stem)."""
    found: dict[str, list[tuple[Path, dict]]] = {}
    for path in sorted((root / EXPERIMENTS).glob("*.yml")):
        data = yaml.safe_load(path.read_text()) or {}
        found.setdefault(str(data.get("name") or path.stem), []).append((path.relative_to(root), data))
    return found


def _commits(results: pd.DataFrame, folder: Path) -> str:
    """The commits the sweep's runs were trained at (their summaries' ``code``), short."""
    commits, unrecorded = set(), 0
    for summary in results.get("summary", pd.Series(dtype=object)).dropna():
        path = folder / str(summary)
        code = json.loads(path.read_text()).get("code") if path.is_file() else None
        if not code:
            unrecorded += 1
        for part in code or []:
            commits.add(str(part.get("commit", ""))[:7] + ("+changes" if part.get("changed") else ""))
    unrecorded += int(results["summary"].isna().sum()) if "summary" in results else len(results)
    text = ", ".join(f"`{commit}`" for commit in sorted(commits))
    if unrecorded:
        text += ("; " if text else "") + (f"{unrecorded} run{'s' if unrecorded > 1 else ''} trained before runs "
                                           "recorded their commit")
    return text


def sweep_section(folder: Path, root: Path, files: list[tuple[Path, dict]], plot: bool) -> str:
    """One sweep's section of the page: commands, commits, table, note, plots (written when ``plot``)."""
    results, cycles_note = break_cycles_note(read_results(folder / "results.csv"), folder)
    lines = [f"## {folder.name}", ""]
    if files:
        lines.append("Reproduce (resumable: a run with a row is skipped), then `python benchmarks/report.py`:")
        lines.append("")
        for path, data in files:
            variants = ", ".join(data.get("variants") or [])
            lines.append(f"- `python -m benchmarks.run {path.as_posix()} --jobs 2` ({variants})")
    else:
        lines.append("No sweep file of `benchmarks/experiments/` writes into this folder.")
    with_subgoals = results.assign(subgoals=subgoal_counts(results, folder))
    lines += ["", f"Trained at: {_commits(results, folder)}.", "", markdown_table(with_subgoals)]
    episodes = sorted(int(value) for value in results["eval_episodes"].dropna().unique()) if "eval_episodes" in results else []
    lines.append(
        f"Mean ± std over seeds. Success: fraction of {' / '.join(map(str, episodes)) or 'the'} fresh evaluation "
        "episodes (seeds seed + 10000, ...) solved by the deterministic and by the stochastic policy. Labels: "
        "preference queries answered (HhP only)."
        + (" Sub-goals: those an HhP run had found at its end." if with_subgoals["subgoals"].notna().any() else "")
        + " Wall time: training and evaluation of one run, on the machine and under the load it had."
        + ("\n" + cycles_note.rstrip() if cycles_note else ""))
    timed = steps_to_level(results, folder)
    if timed:
        lines += ["", f"Steps to {variant_name(REACH_BASELINE)}'s final success (the mean over its seeds, deterministic) or "
                  f"{REACH_CAP}, whichever is lower: the first periodic evaluation of each seed at that level (a run "
                  "that never reached it is left out of the mean).", "", timed.rstrip()]
    if plot:
        plot_curves(results, folder)
    for path in sorted(folder.glob("curves_*.png")):
        lines += ["", f"![{path.stem}]({Path('..', *path.relative_to(root).parts).as_posix()})"]
    return "\n".join(lines) + "\n"


def json_section(paths: Sequence[Path], title: str, intro: str, columns: Sequence[str], aligns: str,
                 row: Callable[[Path, dict], Sequence[str]]) -> str:
    """A section of the page with one table row per JSON results file (none: no section)."""
    if not paths:
        return ""
    lines = [f"## {title}", "", intro, "", "| " + " | ".join(columns) + " |",
             "| " + " | ".join("---:" if align == "r" else "---" for align in aligns) + " |"]
    lines += ["| " + " | ".join(row(path, json.loads(path.read_text()))) + " |" for path in paths]
    return "\n".join(lines) + "\n"


def _calibration_row(path: Path, data: dict) -> list[str]:
    rows = pd.DataFrame(data["rows"])
    return [f"`{path.name}`", _seeds(rows["seed"]), f"{rows['success_rate'].min():.2f}",
            f"{rows['mean_return'].min():.3f}-{rows['mean_return'].max():.3f}",
            f"{int(rows['questions'].min())}-{int(rows['questions'].max())}", "yes" if data.get("kernels") else "no"]


def calibration_section(root: Path) -> str:
    """The CI learning test's calibrations (``benchmarks/calibrate_learning_test.py``'s JSON files)."""
    return json_section(
        sorted((root / RESULTS).glob("learning_test_calibration*.json")), "The CI learning test's calibration",
        "`tests/test_learning.py` trains HhP 8,000 steps on MiniGrid-Empty-Random-5x5 and evaluates 30 fresh episodes; "
        "`python benchmarks/calibrate_learning_test.py --seeds ...` runs it seed by seed (random policy's mean "
        "return: 0.354). `kernels`: the CPU code paths pinned (`tests/conftest.py`).",
        ("file", "seeds", "success rate (lowest)", "mean return (range)", "questions (range)", "kernels pinned"),
        "lrrrrl", _calibration_row)


def _hierarchical_env_row(path: Path, data: dict) -> list[str]:
    return [f"`{path.name}`", data["env"], str(data["seed"]), f"{data['hhp_steps']:,}", str(len(data["subgoals"])),
            str(data["labels"]), *(f"{data[name]['success_rate']:.2f}" for name in ("hhp", "DQN", "PPO")),
            f"{data['meta_steps']:,}"]


def hierarchical_env_section(root: Path) -> str:
    """SB3's algorithms over a trained model's skills (``benchmarks/hierarchical_env.py``'s JSON files)."""
    return json_section(
        sorted((root / RESULTS / "hierarchical_env").glob("*.json")), "SB3 algorithms over HhP's skills (`HierarchicalEnv`)",
        "`python benchmarks/hierarchical_env.py --env ENV --hhp-steps N --meta-steps M --seed S --out FILE` trains HhP "
        "with the env's YAML entry, freezes its sub-goal learners and trains SB3's DQN and PPO on the semi-MDP whose "
        "actions are its sub-goals; success on fresh episodes (seeds from 1,000), stochastic policies.",
        ("file", "env", "seed", "HhP steps", "sub-goals", "labels", "HhP", "DQN", "PPO", "choices each"),
        "llrrrrrrrr", _hierarchical_env_row)


def _code(data: dict) -> str:
    """The commit a measurement ran (``+`` where files of the package differed from it), from ``code_version``."""
    code = data.get("code")
    return "–" if not code else code["commit"][:7] + ("+" if code["changed"] else "")


def _speed_row(path: Path, data: dict) -> list[str]:
    name, fps = ("DDPG + HER", data["her_fps"]) if "her_fps" in data else ("DQN", data.get("dqn_fps"))
    return [f"`{path.name}`", _code(data), data["env"], str(data.get("n_envs", 1)), f"{data['window'][0]:,}-{data['window'][1]:,}",
            f"`{json.dumps(data.get('hhp_kwargs') or {})}`", f"{data['hhp_fps']:.1f}",
            f"{name} {fps:.1f}" if fps is not None else "–", f"{data['ratio']:.2f}" if fps is not None else "–",
            str(data.get("num_subgoals", "–")), f"{data['load_average_start']:.1f}-{data['load_average_end']:.1f}"]


def _speed_files(root: Path, key: str) -> list[Path]:
    """``benchmarks/speed.py``'s JSON files under ``results/speed`` that hold ``key``."""
    return [path for path in sorted((root / RESULTS / "speed").glob("*.json")) if key in json.loads(path.read_text())]


def _subgoals_row(path: Path, data: dict) -> list[str]:
    low, high = data["rows"][0], data["rows"][-1]
    return [f"`{path.name}`", _code(data), data["env"], f"{data['window'][0]:,}-{data['window'][1]:,}",
            f"`{json.dumps(data.get('hhp_kwargs') or {})}`", f"{low['k']} / {high['k']}",
            f"{low['ms_per_step']:.1f} / {high['ms_per_step']:.1f}", f"{data['cost_ratio']:.2f}",
            f"{low['replay_mb']:.0f} / {high['replay_mb']:.0f}", f"{data['memory_ratio']:.2f}"]


def _contact_row(path: Path, data: dict) -> list[str]:
    names = [subgoal["name"] for subgoal in data["subgoals"]]
    return [f"`{path.parent.name}/{path.name}`", data["env"], f"{data['num_timesteps']:,}", str(data["episodes"]),
            "deterministic" if data["deterministic"] else "stochastic", f"{data['gripper_at_object']:.2f}",
            f"{data['object_moved']:.2f}", f"{data['success']:.2f}",
            f"{len(names)} ({sum(name.endswith('the gripper at it') for name in names)})"]


def contact_section(root: Path) -> str:
    """Fresh episodes of saved Fetch models (``benchmarks/diagnostics/fetch_contact.py``'s JSON files beside their
    sweep's results, ``contact_*.json``)."""
    return json_section(
        sorted((root / RESULTS).glob("*/contact_*.json")), "Fetch: the gripper at the object",
        "`python benchmarks/diagnostics/fetch_contact.py --model RUN/model.zip --env ENV --out FILE`: fresh episodes "
        "(seeds 10000, 10001, ...) of a saved model's policy; the share where the gripper came within 5 cm of the object, where "
        "the object moved more than 1 cm, and where the task was solved at the end; the model's sub-goals (with the "
        "gripper at the object).",
        ("file", "env", "steps", "episodes", "policy", "gripper at object", "object moved", "solved", "sub-goals"),
        "llrrlrrrr", _contact_row)


def speed_section(root: Path) -> str:
    """HhP's steps per second beside SB3's DQN, and the cost of many sub-goals (``benchmarks/speed.py``'s JSON files
    under ``results/speed``: ``entry --vs-dqn`` and ``subgoals``)."""
    subgoals = json_section(
        _speed_files(root, "cost_ratio"), "The cost of many sub-goals",
        "`python benchmarks/speed.py subgoals --env ENV --start A --stop B --hhp-kwargs JSON --name NAME`: HhP with K "
        "sub-goals handed in (discovery off; on Atari no questions), each K in a fresh process, timed over steps A-B; "
        "the cost of a primitive step, the sub-goal learners' replay and the peak resident memory (ratio).",
        ("file", "code", "env", "steps", "HhP arguments", "sub-goals", "ms a step", "cost ratio", "replay MB", "memory ratio"),
        "lllrlrrrrr", _subgoals_row)
    return json_section(
        _speed_files(root, "hhp_fps"), "Speed beside SB3's DQN and DDPG + HER",
        "`python benchmarks/speed.py entry --env ENV --start A --stop B --vs-dqn --hhp-kwargs JSON --name NAME` times HhP "
        "as the env's YAML entry trains it (with the arguments shown over the entry's; its questions paced over the "
        "entry's n_timesteps, as in the run the window is part of, where files measured before "
        "`montezuma_entry_landmarks.json` paced the whole budget over the B steps) and SB3's DQN on the same envs "
        "(train_freq 4, batch 32) over primitive steps A-B, in one process, one torch thread; `--vs-her` instead of "
        "`--vs-dqn` times SB3's DDPG + HER with the sub-goal learner's settings (the file's `her`). "
        "The baseline's figure is the mean of its window before and after HhP's. The load average is the machine's "
        "(2 cores) at the start and the end; code: the commit measured.",
        ("file", "code", "env", "envs", "steps", "HhP arguments", "HhP steps/s", "baseline steps/s", "ratio", "sub-goals",
         "load"),
        "lllrrlrrrrr", _speed_row) + ("\n" + subgoals if subgoals else "")


def results_page(root: Path = ROOT, plot: bool = False) -> str:
    """The results page's text (and, with ``plot``, each sweep's learning curves written)."""
    folders = sorted(path.parent for path in (root / RESULTS).glob("*/results.csv"))
    if not folders:
        raise SystemExit(f"No {RESULTS}/*/results.csv yet: run python -m benchmarks.run CONFIG first")
    files = sweep_files(root)
    sections = [
        "# Results", "",
        "Generated by `python benchmarks/report.py` from every sweep under `benchmarks/results/`: do not edit by hand "
        "(`python benchmarks/report.py --check` says whether this page and the summaries in `README.md`, "
        "`docs/modules/hhp.rst` and `benchmarks/README.md` are up to date). How to run a sweep: `benchmarks/README.md`.",
        "", "## Where each task stands", "", markdown_summary(summary_rows(root)),
    ]
    sections += [sweep_section(folder, root, files.get(folder.name, []), plot) for folder in folders]
    sections.append(contact_section(root))
    sections.append(hierarchical_env_section(root))
    sections.append(speed_section(root))
    sections.append(calibration_section(root))
    return "\n".join(section for section in sections if section).rstrip() + "\n"


def with_block(text: str, markup: str, block: str, path: Path) -> str:
    """``text`` with what lies between its two markers replaced by ``block``."""
    begin, end = MARKERS[markup]
    pattern = re.compile(rf"^{re.escape(begin)}[ \t]*\n.*?^{re.escape(end)}[ \t]*$", re.DOTALL | re.MULTILINE)
    if len(pattern.findall(text)) != 1:
        raise SystemExit(f"{path} needs one block between a line {begin!r} and a line {end!r}")
    return pattern.sub(lambda _: f"{begin}\n\n{block}\n{end}", text)


def expected_files(root: Path = ROOT, plot: bool = False) -> dict[Path, str]:
    """Every file the report writes (the page, the three files with a marked block), with the text it should have."""
    rows = summary_rows(root)
    blocks = {"md": markdown_summary(rows), "rst": rst_summary(rows)}
    expected = {root / PAGE: results_page(root, plot)}
    for path, markup in BLOCKS.items():
        expected[root / path] = with_block((root / path).read_text(), markup, blocks[markup], path)
    return expected


def write_or_check(root: Path = ROOT, check: bool = False) -> list[Path]:
    """Write the page and the marked blocks (and the plots), or, with ``check``, write nothing.

    :return: the files that were (``check``: that are) out of date
    """
    stale = []
    for path, text in expected_files(root, plot=not check).items():
        if not path.is_file() or path.read_text() != text:
            stale.append(path)
            if not check:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(text)
    return stale


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "results", nargs="*", help="one sweep's results.csv files (or their folders): benchmark.md and plots next to each"
    )
    parser.add_argument("--check", action="store_true",
                        help=f"write nothing; exit 1 if {PAGE} or a marked block is not what the results give")
    parser.add_argument("--root", type=Path, default=ROOT, help="the repository's root (default: this checkout)")
    args = parser.parse_args(argv)
    if args.results:
        paths = [Path(path) for path in args.results]
        for path in [path / "results.csv" if path.is_dir() else path for path in paths]:
            table, markdown, plots = report(path)
            print(table)
            print(f"Written: {markdown}" + "".join(f", {plot}" for plot in plots))
        return 0
    if not list((args.root / RESULTS).glob("*/results.csv")):
        print(f"No {RESULTS}/*/results.csv yet: run python -m benchmarks.run CONFIG first", file=sys.stderr)
        return 1
    stale = write_or_check(args.root, check=args.check)
    names = ", ".join(str(path.relative_to(args.root)) for path in stale)
    if args.check:
        if stale:
            print(f"Out of date: {names}. Run python benchmarks/report.py and commit what it writes.", file=sys.stderr)
            return 1
        print(f"Up to date: {PAGE} and the summaries in " + ", ".join(map(str, BLOCKS)))
        return 0
    print(markdown_summary(summary_rows(args.root)))
    print(f"Written: {names}" if stale else "Nothing changed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
