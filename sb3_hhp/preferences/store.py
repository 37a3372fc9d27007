"""The durable preference database R of section 4.1.1: every query (s, g1, g2) and its label v.

:class:`PreferenceStore` keeps the queue of questions asked to people and their answers in one
SQLite file. Every write is committed at once in WAL mode with ``synchronous=FULL``, so killing
the process (even with SIGKILL) never loses an answer that was acknowledged. Several processes
may share the file: the trainer writes queries and reads answers, one or more labeling servers
read queries and write answers. Answers carry a monotonically increasing sequence number so a
trainer reads them incrementally with :meth:`PreferenceStore.answers_since`.

A preference *dataset* (:meth:`PreferenceStore.export`) is a SQLite file with the same schema that
holds only the answered queries and their answers; it can be loaded
(:meth:`PreferenceStore.load_dataset`) or merged into another store without duplicates
(:meth:`PreferenceStore.import_dataset`).
"""

import json
import math
import os
import sqlite3
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from typing import Any, Optional, Union

import numpy as np

from sb3_hhp.preferences.codecs import decode_array, decode_png, encode_array, encode_info, encode_png
from sb3_hhp.preferences.types import Answer, Label, Query

__all__ = ["AlreadyAnswered", "PreferenceStore"]

#: identifies a preference store in its ``meta`` table
STORE_FORMAT = "sb3_hhp.preferences"
#: bumped whenever the schema changes; older files are migrated, newer ones refused
#: (2: sub-goals carry an ``info`` JSON with their name, answers the seconds a person took)
SCHEMA_VERSION = 2
#: the images a query may carry, as named in the API
IMAGE_KINDS = ("state", "goal1", "goal2")

_SQLITE_MAGIC = b"SQLite format 3\x00"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS queries (
    query_id TEXT PRIMARY KEY,
    run_id TEXT NOT NULL DEFAULT '',
    goal1 INTEGER NOT NULL,
    goal2 INTEGER NOT NULL,
    state BLOB NOT NULL,
    goal1_obs BLOB NOT NULL,
    goal2_obs BLOB NOT NULL,
    state_png BLOB,
    goal1_png BLOB,
    goal2_png BLOB,
    info TEXT NOT NULL DEFAULT '{}',
    asked_at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS queries_asked_at ON queries (asked_at);
CREATE TABLE IF NOT EXISTS answers (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    query_id TEXT NOT NULL UNIQUE REFERENCES queries (query_id),
    label INTEGER NOT NULL CHECK (label IN (0, 1, 2, 3)),
    annotator TEXT NOT NULL CHECK (length(annotator) > 0),
    answered_at REAL NOT NULL,
    response_s REAL
);
"""

#: schema migrations: the statements that bring a store of version ``v - 1`` to version ``v``
_MIGRATIONS = {
    2: (
        "ALTER TABLE answers ADD COLUMN response_s REAL",
        # version 1 files hold the sub-goal gallery's table (now sb3_hhp.subgoal_table's) in its first layout
        "ALTER TABLE subgoals ADD COLUMN info TEXT NOT NULL DEFAULT '{}'",
    ),
}

_QUERY_COLUMNS = (
    "query_id, run_id, goal1, goal2, state, goal1_obs, goal2_obs, state_png, goal1_png, goal2_png, info, asked_at"
)


class AlreadyAnswered(ValueError):
    """Raised when a query that already has an answer receives a second one."""


# --------------------------------------------------------------------------------------------


class PreferenceStore:
    """The preference database R (section 4.1.1) in one SQLite file, shared by trainer and annotators.

    :param path: the SQLite file (created when missing) or ``":memory:"`` for a private in-memory store.
        A file that exists but is not a preference store (another SQLite database, a corrupt or
        unrelated file) raises ``ValueError`` and is left untouched.
    :param timeout: seconds to wait for another process's write lock before failing (> 0)
    :param create: create the file when it does not exist; with ``False`` a missing file raises
        ``FileNotFoundError`` and nothing is written (for tools that must open an existing store)
    """

    def __init__(self, path: Union[str, os.PathLike] = ":memory:", timeout: float = 30.0, create: bool = True) -> None:
        if timeout <= 0:
            raise ValueError(f"timeout must be > 0 seconds, got {timeout}")
        self.path = str(path) if str(path) == ":memory:" else os.fspath(path)
        self._lock = threading.RLock()
        if self.path != ":memory:":
            if not create and not os.path.exists(self.path):
                raise FileNotFoundError(f"No preference store at {self.path!r}")
            _check_sqlite_header(self.path)
        try:
            self._conn = sqlite3.connect(self.path, timeout=timeout, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as error:
            raise ValueError(f"Cannot open the preference store {self.path!r}: {error}") from error
        try:
            self._open()
        except sqlite3.DatabaseError as error:
            self._conn.close()
            raise ValueError(
                f"{self.path!r} is not a readable preference store ({error}); choose another path or remove the file"
            ) from error
        except ValueError:
            self._conn.close()
            raise

    # ---------------------------------------------------------------- set-up

    def _open(self) -> None:
        conn = self._conn
        # Reading the schema first makes a non-database file fail before anything is written.
        tables = {row[0] for row in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if tables and "meta" not in tables:
            raise ValueError(
                f"{self.path!r} is an SQLite database but not a preference store (tables: {sorted(tables)}); "
                "choose another path"
            )
        if tables:
            self._check_meta()
        if self.path != ":memory:":
            conn.execute("PRAGMA journal_mode = WAL")
        conn.execute("PRAGMA synchronous = FULL")
        conn.execute("PRAGMA foreign_keys = ON")
        with self._transaction():
            tables = {row[0] for row in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if "meta" not in tables:  # a new store (another process may have created it meanwhile)
                for statement in _SCHEMA.strip().split(";"):
                    if statement.strip():
                        conn.execute(statement)
                conn.execute("INSERT OR IGNORE INTO meta VALUES ('format', ?)", (STORE_FORMAT,))
                conn.execute("INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
                conn.execute("INSERT OR IGNORE INTO meta VALUES ('created_at', ?)", (repr(time.time()),))
        self._check_meta()
        self._migrate()

    def _migrate(self) -> None:
        """Bring a store written by an older sb3_hhp to :data:`SCHEMA_VERSION`, one version at a time."""
        if self._schema_version() >= SCHEMA_VERSION:
            return
        with self._transaction() as conn:  # another process may have migrated it meanwhile: read again
            version = int(conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0])
            for target in range(version + 1, SCHEMA_VERSION + 1):
                for statement in _MIGRATIONS[target]:
                    conn.execute(statement)
                conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(target),))

    def _check_meta(self) -> None:
        meta = dict(self._conn.execute("SELECT key, value FROM meta").fetchall())
        if meta.get("format") != STORE_FORMAT:
            raise ValueError(
                f"{self.path!r} is an SQLite database but not a preference store "
                f"(format {meta.get('format')!r}, expected {STORE_FORMAT!r}); choose another path"
            )
        version = int(meta.get("schema_version", "0"))
        if version > SCHEMA_VERSION:
            raise ValueError(
                f"{self.path!r} has store schema version {version}, newer than this sb3_hhp's {SCHEMA_VERSION}; "
                "upgrade sb3_hhp to read it"
            )
        if version < 1:
            raise ValueError(f"{self.path!r} has an invalid store schema version {version}")

    def _schema_version(self) -> int:
        return int(self._read("SELECT value FROM meta WHERE key = 'schema_version'")[0][0])

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction, committed at once (or rolled back on any error)."""
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            self._conn.execute("COMMIT")

    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple]:
        with self._lock:
            return self._conn.execute(sql, params).fetchall()

    # ---------------------------------------------------------------- tables kept beside the preference data

    def transaction(self) -> AbstractContextManager[sqlite3.Connection]:
        """One write transaction on the store's file, committed at once: for tables that share the file with
        the preference data without being part of it (the sub-goal gallery, :mod:`sb3_hhp.subgoal_table`)."""
        return self._transaction()

    def read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple]:
        """The rows of one read-only statement on the store's file (see :meth:`transaction`)."""
        return self._read(sql, params)

    # ---------------------------------------------------------------- queries

    def add_query(self, query: Query, run_id: str = "") -> None:
        """Store a query (the question asked); a query whose ``query_id`` is stored already is ignored.

        :param query: the question; its observations are stored as ``.npy`` bytes, its images as PNG,
            its ``info`` as JSON (numpy values become plain numbers and lists)
        :param run_id: the training run that asked it, for :meth:`count_asked`
        """
        if not isinstance(query, Query):
            raise ValueError(f"add_query expects a Query, got {type(query).__name__}")
        if not isinstance(run_id, str):
            raise ValueError(f"run_id must be a string, got {type(run_id).__name__}")
        row = (
            str(query.query_id),
            run_id,
            int(query.goal1),
            int(query.goal2),
            encode_array(query.state, "Query.state"),
            encode_array(query.goal1_obs, "Query.goal1_obs"),
            encode_array(query.goal2_obs, "Query.goal2_obs"),
            None if query.state_image is None else encode_png(query.state_image, "Query.state_image"),
            None if query.goal1_image is None else encode_png(query.goal1_image, "Query.goal1_image"),
            None if query.goal2_image is None else encode_png(query.goal2_image, "Query.goal2_image"),
            encode_info(query.info),
            float(query.asked_at),
        )
        with self._transaction() as conn:
            conn.execute(f"INSERT OR IGNORE INTO queries ({_QUERY_COLUMNS}) VALUES ({', '.join('?' * 12)})", row)

    def get_query(self, query_id: str) -> Query:
        """The stored query ``query_id`` (``KeyError`` when unknown)."""
        rows = self._read(f"SELECT {_QUERY_COLUMNS} FROM queries WHERE query_id = ?", (query_id,))
        if not rows:
            raise KeyError(f"Unknown query id {query_id!r}")
        return _row_to_query(rows[0])

    def open_query_ids(self, limit: Optional[int] = None) -> list[str]:
        """Ids of the asked and unanswered queries, oldest first (cheap: no arrays are decoded)."""
        sql = (
            "SELECT q.query_id FROM queries q LEFT JOIN answers a ON a.query_id = q.query_id "
            "WHERE a.query_id IS NULL ORDER BY q.asked_at, q.rowid"
        )
        params: tuple = ()
        if limit is not None:
            sql += " LIMIT ?"
            params = (int(limit),)
        return [row[0] for row in self._read(sql, params)]

    def open_queries(self, limit: Optional[int] = None) -> list[Query]:
        """The asked and unanswered queries, oldest first.

        :param limit: at most this many (all when ``None``)
        """
        if limit is not None and limit < 0:
            raise ValueError(f"limit must be >= 0, got {limit}")
        sql = (
            f"SELECT {', '.join('q.' + c.strip() for c in _QUERY_COLUMNS.split(','))} FROM queries q "
            "LEFT JOIN answers a ON a.query_id = q.query_id WHERE a.query_id IS NULL ORDER BY q.asked_at, q.rowid"
        )
        params: tuple = ()
        if limit is not None:
            sql += " LIMIT ?"
            params = (int(limit),)
        return [_row_to_query(row) for row in self._read(sql, params)]

    def query_info(self, query_id: str) -> dict:
        """The ``info`` dict of a stored query, without decoding its arrays and images (``KeyError`` when unknown)."""
        rows = self._read("SELECT info FROM queries WHERE query_id = ?", (query_id,))
        if not rows:
            raise KeyError(f"Unknown query id {query_id!r}")
        return json.loads(rows[0][0])

    def query_goals(self, query_id: str) -> tuple[int, int, float]:
        """A stored query's ``(goal1, goal2, asked_at)``, without decoding its arrays (``KeyError`` when unknown)."""
        rows = self._read("SELECT goal1, goal2, asked_at FROM queries WHERE query_id = ?", (query_id,))
        if not rows:
            raise KeyError(f"Unknown query id {query_id!r}")
        return int(rows[0][0]), int(rows[0][1]), float(rows[0][2])

    def is_open(self, query_id: str) -> bool:
        """Whether ``query_id`` was asked and has no answer yet."""
        rows = self._read(
            "SELECT a.seq FROM queries q LEFT JOIN answers a ON a.query_id = q.query_id WHERE q.query_id = ?",
            (query_id,),
        )
        return bool(rows) and rows[0][0] is None

    # ---------------------------------------------------------------- answers

    def add_answer(
        self,
        query_id: str,
        label: Union[Label, int, str],
        annotator: str,
        answered_at: Optional[float] = None,
        response_s: Optional[float] = None,
    ) -> Answer:
        """Record the answer to a stored query, committed before returning.

        Raises ``KeyError`` for an unknown ``query_id``, ``ValueError`` for a bad label or an empty
        annotator, and :class:`AlreadyAnswered` when the query has an answer already; on any error
        the store is unchanged.

        :param query_id: the query answered
        :param label: FIRST, SECOND, EQUAL or INCOMPARABLE, as a :class:`~sb3_hhp.preferences.types.Label`, its name or its value
        :param annotator: who answered (non-empty)
        :param answered_at: UNIX time of the answer (now when ``None``)
        :param response_s: seconds the person took from seeing the question to answering (>= 0; ``None``
            when unknown, e.g. for a scripted oracle)
        :return: the stored answer
        """
        parsed = Label.parse(label)
        if not isinstance(annotator, str) or not annotator.strip():
            raise ValueError(f"annotator must be a non-empty string naming who answered, got {annotator!r}")
        annotator = annotator.strip()
        answered_at = time.time() if answered_at is None else float(answered_at)
        if response_s is not None:
            response_s = float(response_s)
            if not (math.isfinite(response_s) and response_s >= 0):
                raise ValueError(f"response_s must be a finite number of seconds >= 0 or None, got {response_s}")
        with self._transaction() as conn:
            if conn.execute("SELECT 1 FROM queries WHERE query_id = ?", (query_id,)).fetchone() is None:
                raise KeyError(f"Unknown query id {query_id!r}: add the query before its answer")
            previous = conn.execute("SELECT annotator FROM answers WHERE query_id = ?", (query_id,)).fetchone()
            if previous is not None:
                raise AlreadyAnswered(f"Query {query_id!r} was already answered by {previous[0]!r}")
            conn.execute(
                "INSERT INTO answers (query_id, label, annotator, answered_at, response_s) VALUES (?, ?, ?, ?, ?)",
                (query_id, int(parsed), annotator, answered_at, response_s),
            )
        return Answer(query_id, parsed, annotator, answered_at)

    def answers_since(self, seq: int = 0) -> list[tuple[int, Query, Answer]]:
        """Answered queries whose answer has a sequence number above ``seq``, in commit order.

        A trainer keeps the last sequence number it saw and passes it back to read only new answers.

        :param seq: the last sequence number already read (0 reads everything)
        :return: ``(seq, query, answer)`` triples, ``seq`` strictly increasing
        """
        rows = self._read(
            f"SELECT a.seq, a.label, a.annotator, a.answered_at, "
            f"{', '.join('q.' + c.strip() for c in _QUERY_COLUMNS.split(','))} "
            "FROM answers a JOIN queries q ON q.query_id = a.query_id WHERE a.seq > ? ORDER BY a.seq",
            (int(seq),),
        )
        result = []
        for row in rows:
            query = _row_to_query(row[4:])
            result.append((int(row[0]), query, Answer(query.query_id, Label(row[1]), row[2], float(row[3]))))
        return result

    def last_seq(self) -> int:
        """The sequence number of the newest answer (0 when there is none)."""
        return int(self._read("SELECT COALESCE(MAX(seq), 0) FROM answers")[0][0])

    def get_answer(self, query_id: str) -> Optional[Answer]:
        """The answer to ``query_id``, or ``None`` while it is open (``KeyError`` for an unknown id)."""
        rows = self._read(
            "SELECT q.query_id, a.label, a.annotator, a.answered_at FROM queries q "
            "LEFT JOIN answers a ON a.query_id = q.query_id WHERE q.query_id = ?",
            (query_id,),
        )
        if not rows:
            raise KeyError(f"Unknown query id {query_id!r}")
        query_id, label, annotator, answered_at = rows[0]
        return None if label is None else Answer(query_id, Label(label), annotator, float(answered_at))

    def asked_ids(self) -> set[str]:
        """Ids of every stored query, answered or not."""
        return {row[0] for row in self._read("SELECT query_id FROM queries")}

    def question_goals(self) -> list[tuple[int, int, Optional[Label]]]:
        """Every stored query's ``(goal1, goal2, label)``, ``label`` ``None`` while unanswered, in one read and
        without decoding the queries' arrays."""
        rows = self._read("SELECT q.goal1, q.goal2, a.label FROM queries q LEFT JOIN answers a ON a.query_id = q.query_id")
        return [(int(goal1), int(goal2), None if label is None else Label(label)) for goal1, goal2, label in rows]

    def answered_ids(self) -> set[str]:
        """Ids of the answered queries."""
        return {row[0] for row in self._read("SELECT query_id FROM answers")}

    def count_asked(self, run_id: Optional[str] = None) -> int:
        """How many queries were asked (by the run ``run_id``, or by all runs when ``None``)."""
        if run_id is None:
            return int(self._read("SELECT COUNT(*) FROM queries")[0][0])
        return int(self._read("SELECT COUNT(*) FROM queries WHERE run_id = ?", (run_id,))[0][0])

    def stats(self) -> dict:
        """Counts: ``asked``, ``queued`` (open), ``answered``, ``per_annotator`` and ``per_label`` answers,
        the run's ``budget`` (:meth:`set_query_budget`, ``None`` when unknown), and ``distinct``: how many
        different questions (``info["signature"]``: an equivalent state and an unordered pair of sub-goals)
        are among the ``signed`` queries that carry a signature (``None`` when none does)."""
        with self._lock:
            asked = int(self._conn.execute("SELECT COUNT(*) FROM queries").fetchone()[0])
            per_annotator = dict(
                self._conn.execute("SELECT annotator, COUNT(*) FROM answers GROUP BY annotator ORDER BY annotator")
            )
            per_label = dict(self._conn.execute("SELECT label, COUNT(*) FROM answers GROUP BY label"))
            distinct, signed = self._conn.execute(
                "SELECT COUNT(DISTINCT s), COUNT(s) FROM (SELECT json_extract(info, '$.signature') AS s FROM queries "
                "WHERE json_valid(info))"
            ).fetchone()
        answered = sum(per_annotator.values())
        return {
            "asked": asked,
            "queued": asked - answered,
            "answered": answered,
            "per_annotator": {str(name): int(count) for name, count in per_annotator.items()},
            "per_label": {label.name: int(per_label.get(int(label), 0)) for label in Label},
            "budget": self.query_budget(),
            "distinct": int(distinct) if signed else None,
            "signed": int(signed),
        }

    def set_query_budget(self, budget: int) -> None:
        """Record the run's total query budget, shown on the labeling page as "asked / budget".

        :param budget: the total number of questions the run may ask (>= 0)
        """
        if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 0:
            raise ValueError(f"budget must be an integer >= 0, got {budget!r}")
        with self._transaction() as conn:
            conn.execute("INSERT OR REPLACE INTO meta VALUES ('query_budget', ?)", (str(int(budget)),))

    def query_budget(self) -> Optional[int]:
        """The query budget recorded by :meth:`set_query_budget` (``None`` when none was)."""
        rows = self._read("SELECT value FROM meta WHERE key = 'query_budget'")
        return int(rows[0][0]) if rows else None

    def response_times(self, annotator: Optional[str] = None) -> list[float]:
        """Seconds each answer took its person (answers recorded with ``response_s``), oldest first.

        :param annotator: only this annotator's answers (everyone's when ``None``)
        """
        if annotator is None:
            rows = self._read("SELECT response_s FROM answers WHERE response_s IS NOT NULL ORDER BY seq")
        else:
            rows = self._read(
                "SELECT response_s FROM answers WHERE response_s IS NOT NULL AND annotator = ? ORDER BY seq",
                (annotator,),
            )
        return [float(row[0]) for row in rows]

    def image_png(self, query_id: str, which: str) -> bytes:
        """The PNG bytes of a query's image.

        :param query_id: the query
        :param which: ``"state"``, ``"goal1"`` or ``"goal2"``
        :raises KeyError: unknown query, or that image was not stored with it
        """
        if which not in IMAGE_KINDS:
            raise ValueError(f"which must be one of {IMAGE_KINDS}, got {which!r}")
        rows = self._read(f"SELECT {which}_png FROM queries WHERE query_id = ?", (query_id,))
        if not rows:
            raise KeyError(f"Unknown query id {query_id!r}")
        if rows[0][0] is None:
            raise KeyError(f"Query {query_id!r} has no {which} image")
        return bytes(rows[0][0])

    def image_kinds(self, query_id: str) -> list[str]:
        """Which of ``state``, ``goal1``, ``goal2`` have an image stored for ``query_id``."""
        rows = self._read("SELECT state_png IS NOT NULL, goal1_png IS NOT NULL, goal2_png IS NOT NULL "
                          "FROM queries WHERE query_id = ?", (query_id,))
        if not rows:
            raise KeyError(f"Unknown query id {query_id!r}")
        return [kind for kind, present in zip(IMAGE_KINDS, rows[0]) if present]

    # ---------------------------------------------------------------- datasets

    def export(self, path: Union[str, os.PathLike]) -> None:
        """Write the answered queries and their answers to a new preference dataset file.

        The file is a preference store (SQLite, same schema) holding no open query (and no sub-goal gallery).

        :param path: where to write; must not exist yet
        """
        path = os.fspath(path)
        if os.path.exists(path):
            raise FileExistsError(f"{path!r} exists already; remove it or export to another path")
        partial = f"{path}.partial-{os.getpid()}"
        PreferenceStore(partial).close()
        try:
            with self._lock:
                self._conn.execute("ATTACH DATABASE ? AS dst", (partial,))
                try:
                    with self._transaction() as conn:
                        conn.execute(
                            f"INSERT INTO dst.queries ({_QUERY_COLUMNS}) SELECT "
                            f"{', '.join('q.' + c.strip() for c in _QUERY_COLUMNS.split(','))} "
                            "FROM queries q JOIN answers a ON a.query_id = q.query_id ORDER BY a.seq"
                        )
                        conn.execute(
                            "INSERT INTO dst.answers (query_id, label, annotator, answered_at, response_s) "
                            "SELECT query_id, label, annotator, answered_at, response_s FROM answers ORDER BY seq"
                        )
                finally:
                    self._conn.execute("DETACH DATABASE dst")
            # One self-contained file: leave WAL mode so no -wal/-shm file travels with it.
            conn = sqlite3.connect(partial, isolation_level=None)
            try:
                conn.execute("PRAGMA journal_mode = DELETE")
            finally:
                conn.close()
            os.replace(partial, path)
        finally:
            for leftover in (partial, partial + "-wal", partial + "-shm", partial + "-journal"):
                if os.path.exists(leftover):
                    os.remove(leftover)

    @classmethod
    def load_dataset(cls, path: Union[str, os.PathLike]) -> list[tuple[Query, Answer]]:
        """Read the answered queries of a dataset (or of any store file), in answer order.

        :param path: a file written by :meth:`export` (or a store's own file)
        """
        path = os.fspath(path)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"No preference dataset at {path!r}")
        store = cls(path)
        try:
            return [(query, answer) for _, query, answer in store.answers_since(0)]
        finally:
            store.close()

    def import_dataset(self, path: Union[str, os.PathLike]) -> int:
        """Merge a dataset's answered queries into this store, skipping what is answered here already.

        A query asked here and still open receives the dataset's answer.

        :param path: a file written by :meth:`export` (or a store's own file)
        :return: the number of answers added
        """
        path = os.fspath(path)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"No preference dataset at {path!r}")
        PreferenceStore(path).close()  # validates the file (format and schema version) and migrates it
        with self._lock:
            self._conn.execute("ATTACH DATABASE ? AS src", (path,))
            try:
                with self._transaction() as conn:
                    conn.execute(
                        f"INSERT OR IGNORE INTO queries ({_QUERY_COLUMNS}) SELECT "
                        f"{', '.join('q.' + c.strip() for c in _QUERY_COLUMNS.split(','))} "
                        "FROM src.queries q JOIN src.answers a ON a.query_id = q.query_id ORDER BY a.seq"
                    )
                    before = conn.total_changes
                    conn.execute(
                        "INSERT OR IGNORE INTO answers (query_id, label, annotator, answered_at, response_s) "
                        "SELECT query_id, label, annotator, answered_at, response_s FROM src.answers ORDER BY seq"
                    )
                    added = conn.total_changes - before
            finally:
                self._conn.execute("DETACH DATABASE src")
        return int(added)

    # ---------------------------------------------------------------- life cycle

    def close(self) -> None:
        """Close the database connection (everything is committed already)."""
        with self._lock:
            self._conn.close()

    def __enter__(self) -> "PreferenceStore":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"PreferenceStore({self.path!r})"


def _check_sqlite_header(path: str) -> None:
    """Refuse, before SQLite touches it, a non-empty file that is not an SQLite database."""
    if not os.path.exists(path):
        return
    if os.path.isdir(path):
        raise ValueError(f"{path!r} is a directory; pass the path of a preference store file")
    with open(path, "rb") as handle:
        header = handle.read(len(_SQLITE_MAGIC))
    if header and header != _SQLITE_MAGIC:
        raise ValueError(
            f"{path!r} exists but is not a preference store (not an SQLite file, or corrupt); "
            "choose another path or remove the file"
        )


def _row_to_query(row: Sequence[Any]) -> Query:
    (query_id, _run_id, goal1, goal2, state, goal1_obs, goal2_obs, state_png, goal1_png, goal2_png, info, asked_at) = row
    return Query(
        state=decode_array(state),
        goal1=int(goal1),
        goal2=int(goal2),
        goal1_obs=decode_array(goal1_obs),
        goal2_obs=decode_array(goal2_obs),
        state_image=None if state_png is None else decode_png(bytes(state_png)),
        goal1_image=None if goal1_png is None else decode_png(bytes(goal1_png)),
        goal2_image=None if goal2_png is None else decode_png(bytes(goal2_png)),
        info=json.loads(info),
        query_id=query_id,
        asked_at=float(asked_at),
    )
