"""Serve the labeling page over a preference store: ``python -m sb3_hhp.label --db PATH``.

Run it beside a training run that uses ``WebOracle`` on the same ``--db`` file; open the printed
address in a browser (several annotators may share it, each under their own name). A ``--db`` path
that does not exist is refused (a mistyped path would otherwise serve a new, empty store that no
training run writes to) unless ``--create`` asks for a new store.
"""

import argparse
import os
import sys
from typing import Optional

import uvicorn

from sb3_hhp.label.app import create_app
from sb3_hhp.label.server import check_bind
from sb3_hhp.preferences.store import PreferenceStore


def parse_args(argv: Optional[list[str]] = None) -> argparse.Namespace:
    """Command-line arguments of ``python -m sb3_hhp.label``."""
    parser = argparse.ArgumentParser(prog="python -m sb3_hhp.label", description=__doc__.splitlines()[0])
    parser.add_argument("--db", required=True, help="the preference store (SQLite file) shared with training")
    parser.add_argument(
        "--create", action="store_true", help="create an empty store when --db does not exist (refused otherwise)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (anything but loopback needs --token)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port (0 picks a free one)")
    parser.add_argument("--token", default=None, help="access token required by every API call")
    parser.add_argument(
        "--reply-window", type=float, default=5.0, help="seconds per question before the page answers CAN'T TELL"
    )
    return parser.parse_args(argv)


def main(argv: Optional[list[str]] = None) -> int:
    """Serve until interrupted; return the exit status."""
    args = parse_args(argv)
    try:
        check_bind(args.host, args.token)
        if args.create and not os.path.isdir(os.path.dirname(os.path.abspath(args.db))):
            raise ValueError(f"Cannot create {args.db!r}: its folder does not exist; create the folder first")
        store = PreferenceStore(args.db, create=args.create)
    except FileNotFoundError:
        print(
            f"error: there is no preference store at {args.db!r}. Check the path (it is the training run's "
            "preference_db); to start a new, empty store there, pass --create",
            file=sys.stderr,
        )
        return 2
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    try:
        app = create_app(store, token=args.token, reply_window_s=args.reply_window)
    except ValueError as error:
        store.close()
        print(f"error: {error}", file=sys.stderr)
        return 2
    host = f"[{args.host}]" if ":" in args.host else args.host
    suffix = f"?token={args.token}" if args.token else ""
    print(f"Labeling page: http://{host}:{args.port}/{suffix}  (gallery: /gallery{suffix})", flush=True)
    try:
        uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    finally:
        store.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
