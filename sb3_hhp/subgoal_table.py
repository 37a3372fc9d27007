"""The sub-goal gallery's table: what the labeling page's gallery shows, kept in the preference store's file.

The trainer replaces the whole table now and then (:meth:`SubgoalTable.put`); the labeling server reads it
(:meth:`SubgoalTable.records`, :meth:`SubgoalTable.png`). It shares the store's SQLite file (and, for an
in-memory store, its connection) so that one file is all a run and its annotators exchange, but it is not
preference data: :meth:`~sb3_hhp.preferences.store.PreferenceStore.export` leaves it behind.

Each record is a dict: ``id`` (int), ``image`` (RGB uint8 array), ``found_at`` (env step it was found),
``success_rate`` (its subpolicy's, in [0, 1], or ``None``), ``chosen_recently`` (how often the meta-controller
chose it lately), ``mean_score`` (the preference predictor's mean score, or ``None``), ``name`` (what it is, in
words, or ``None``).
"""

import json
import math
from collections.abc import Sequence
from typing import Any, Optional

from sb3_hhp.preferences.codecs import decode_png, encode_info, encode_png
from sb3_hhp.preferences.store import PreferenceStore

__all__ = ["MAX_SUBGOAL_ID", "SubgoalTable"]

#: the largest sub-goal id SQLite can hold (a signed 64-bit integer)
MAX_SUBGOAL_ID = 2**63 - 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS subgoals (
    id INTEGER PRIMARY KEY,
    png BLOB NOT NULL,
    found_at INTEGER,
    success_rate REAL,
    chosen_recently INTEGER NOT NULL DEFAULT 0,
    mean_score REAL,
    info TEXT NOT NULL DEFAULT '{}'
)
"""


def _optional_float(value: Any) -> Optional[float]:
    if value is None:
        return None
    value = float(value)
    return None if math.isnan(value) else value


class SubgoalTable:
    """The sub-goal gallery's records in the file of ``store`` (the table is created when missing).

    :param store: the preference store whose file holds the table
    """

    def __init__(self, store: PreferenceStore) -> None:
        if not isinstance(store, PreferenceStore):
            raise ValueError(f"SubgoalTable needs a PreferenceStore, got {type(store).__name__}")
        self.store = store
        with store.transaction() as conn:
            conn.execute(_SCHEMA)

    def put(self, records: Sequence[dict]) -> None:
        """Replace the records as a whole (a record set with an error changes nothing).

        :param records: one dict per sub-goal (see the module's docstring); ``id`` and ``image`` are required
        """
        rows = []
        seen: set[int] = set()
        for index, record in enumerate(records):
            if "id" not in record or "image" not in record:
                raise ValueError(f"Sub-goal record {index} needs at least 'id' and 'image', got keys {sorted(record)}")
            subgoal_id = int(record["id"])
            if not 0 <= subgoal_id <= MAX_SUBGOAL_ID:
                raise ValueError(f"Sub-goal id must be in [0, {MAX_SUBGOAL_ID}], got {subgoal_id}")
            if subgoal_id in seen:
                raise ValueError(f"Sub-goal id {subgoal_id} appears twice in the records")
            seen.add(subgoal_id)
            found_at = record.get("found_at")
            rows.append(
                (
                    subgoal_id,
                    encode_png(record["image"], f"sub-goal {subgoal_id}'s image"),
                    None if found_at is None else int(found_at),
                    _optional_float(record.get("success_rate")),
                    int(record.get("chosen_recently") or 0),
                    _optional_float(record.get("mean_score")),
                    encode_info({} if record.get("name") is None else {"name": str(record["name"])}),
                )
            )
        with self.store.transaction() as conn:
            conn.execute("DELETE FROM subgoals")
            conn.executemany(
                "INSERT INTO subgoals (id, png, found_at, success_rate, chosen_recently, mean_score, info) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                rows,
            )

    def records(self, with_images: bool = True) -> list[dict]:
        """The records as written by :meth:`put`, ordered by id.

        :param with_images: decode each ``image`` (RGB array); without, records have no ``image`` key
        """
        columns = "id, found_at, success_rate, chosen_recently, mean_score, info" + (", png" if with_images else "")
        records = []
        for row in self.store.read(f"SELECT {columns} FROM subgoals ORDER BY id"):
            record = {
                "id": int(row[0]),
                "found_at": row[1],
                "success_rate": row[2],
                "chosen_recently": int(row[3]),
                "mean_score": row[4],
                "name": json.loads(row[5]).get("name"),
            }
            if with_images:
                record["image"] = decode_png(bytes(row[6]))
            records.append(record)
        return records

    def png(self, subgoal_id: int) -> bytes:
        """The PNG bytes of sub-goal ``subgoal_id``'s image (``KeyError`` when unknown, out of range included)."""
        if not 0 <= int(subgoal_id) <= MAX_SUBGOAL_ID:
            raise KeyError(f"Unknown sub-goal id {subgoal_id}: ids are in [0, {MAX_SUBGOAL_ID}]")
        rows = self.store.read("SELECT png FROM subgoals WHERE id = ?", (int(subgoal_id),))
        if not rows:
            raise KeyError(f"Unknown sub-goal id {subgoal_id}")
        return bytes(rows[0][0])

    def __repr__(self) -> str:
        return f"SubgoalTable({self.store!r})"
