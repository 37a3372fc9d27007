"""Gather benchmark JSONs into a Markdown table and a learning-curve plot.

    python benchmarks/report.py benchmarks/results/doorkey8x8_partial --plot benchmarks/results/doorkey8x8_partial/curves.png
"""

import argparse
import json
import pathlib


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", help="folder of result JSONs written by benchmarks/doorkey.py")
    parser.add_argument("--plot", default=None, help="write a success-rate-over-steps plot here (PNG)")
    parser.add_argument("--subgoals", nargs="*", default=None, metavar="NAME",
                        help="also tabulate, per HhP run, when these sub-goals were found and their success rate at the "
                             "last evaluation (needs evaluations that list sub-goals, as doorkey.py writes them)")
    args = parser.parse_args()
    results = [json.loads(path.read_text()) for path in sorted(pathlib.Path(args.folder).glob("*.json"))]
    results = [r for r in results if "evaluations" in r]
    several_envs = len({r["env"] for r in results}) > 1
    print("| run | seed | steps | fps | success rate | mean return | eval episodes | queries | sub-goals |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in results:
        name = r["algo"] + (f" ({r['tag']})" if r.get("tag") else "")
        if several_envs:
            name += " " + r["env"].replace("MiniGrid-", "").replace("-v0", "")
        queries = f"{r['queries_used']}/{r['query_budget']}" if "queries_used" in r else "-"
        print(f"| {name} | {r['seed']} | {r['total_timesteps']} | {r['fps']} | {r['success_rate']:.2f} | "
              f"{r['mean_return']:.3f} | {r['eval_episodes']} | {queries} | {r.get('num_subgoals', '-')} |")
    if args.subgoals:
        print()
        print("| run | seed | steps | " + " | ".join(args.subgoals) + " |")
        print("| --- " * (3 + len(args.subgoals)) + "|")
        for r in results:
            found = r["evaluations"][-1].get("subgoals") if r["evaluations"] else None
            if found is None:
                continue
            cells = []
            for name in args.subgoals:
                entry = found.get(name)
                if entry is None:
                    cells.append("not found")
                else:
                    rate = "-" if entry["success"] is None else f"{entry['success']:.2f}"
                    cells.append(f"{rate} (found at {entry['found_at']:,})")
            print(f"| {r['algo']} ({r.get('tag', '')}) | {r['seed']} | {r['evaluations'][-1]['timesteps']:,} | " + " | ".join(cells) + " |")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4))
        for r in results:
            steps = [e["timesteps"] for e in r["evaluations"]]
            success = [e["success_rate"] for e in r["evaluations"]]
            ax.plot(steps, success, marker="o", label=f"{r['algo']} {r.get('tag', '')} {r['env'].replace('MiniGrid-', '')} s{r['seed']}")
        ax.set_xlabel("primitive env steps")
        ax.set_ylabel("success rate (fresh seeds)")
        ax.set_ylim(-0.05, 1.05)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=100)


if __name__ == "__main__":
    main()
