"""A person at a terminal (no browser needed) answers preference queries, without ever blocking training."""

import os
import queue
import re
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from typing import Optional, TextIO, Union

import cv2
import numpy as np

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query

# what a person may type (case-insensitive); the names of Label ("first", "equal", "can't tell"...) work too
REPLIES = {
    "1": Label.FIRST,
    "left": Label.FIRST,
    "2": Label.SECOND,
    "right": Label.SECOND,
    "=": Label.EQUAL,
    "x": Label.INCOMPARABLE,
}
PROMPT = "Which sub-goal is better in this state? [1/left, 2/right, = equally good, x can't tell]"
RESET = "\x1b[0m"
UPPER_HALF_BLOCK = "\u2580"


def parse_reply(line: str) -> Optional[Label]:
    """Read a person's reply: ``1``/``left`` = FIRST, ``2``/``right`` = SECOND, ``=`` = EQUAL, ``x`` = can't tell
    (INCOMPARABLE); a label name also works. Return None when the line means none of these."""
    text = line.strip().lower()
    if text in REPLIES:
        return REPLIES[text]
    if not text or text.isdigit():  # digits other than 1 and 2 are typos, not Label values
        return None
    try:
        return Label.parse(text)
    except ValueError:
        return None


def to_rgb_uint8(image: np.ndarray) -> np.ndarray:
    """Turn an image (H, W), (H, W, 1), (H, W, 3), (H, W, 4) or channel-first, uint8 or float in [0, 1],
    into an (H, W, 3) uint8 RGB array."""
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[-1] not in (1, 3, 4) and array.shape[0] in (1, 3, 4):
        array = np.moveaxis(array, 0, -1)  # channel-first
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    if array.ndim == 2:
        array = np.stack([array] * 3, axis=-1)
    if array.ndim != 3 or array.shape[-1] not in (3, 4):
        raise ValueError(f"Expected an image of shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {np.shape(image)}")
    array = array[..., :3]
    if array.dtype != np.uint8:
        array = array.astype(np.float64)
        if array.size and array.max() <= 1.0:
            array = array * 255.0
        array = np.clip(np.rint(array), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(array)


def ansi_preview(
    images: Sequence[Optional[np.ndarray]], width: int = 24, titles: Optional[Sequence[str]] = None, gap: int = 2
) -> str:
    """Draw images side by side with 24-bit ANSI colours, two pixel rows per character (upper half block:
    foreground = top pixel, background = bottom pixel), each image resized to ``width`` columns.

    :param images: RGB images; None leaves a blank column
    :param width: columns per image (>= 1)
    :param titles: optional title above each image
    :param gap: spaces between images
    :return: the preview, lines separated by newlines
    """
    if width < 1:
        raise ValueError(f"width must be >= 1 column, got {width}")
    blocks: list[list[str]] = []
    for image in images:
        if image is None:
            blocks.append([])
            continue
        rgb = to_rgb_uint8(image)
        height_px, width_px = rgb.shape[:2]
        rows_px = max(2, 2 * int(round(height_px / width_px * width / 2)))  # square pixels, an even count
        shrink = width <= width_px and rows_px <= height_px
        small = cv2.resize(rgb, (width, rows_px), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_NEAREST)
        rows = []
        for y in range(0, rows_px, 2):
            cells = [
                f"\x1b[38;2;{top[0]};{top[1]};{top[2]}m\x1b[48;2;{bottom[0]};{bottom[1]};{bottom[2]}m{UPPER_HALF_BLOCK}"
                for top, bottom in zip(small[y].tolist(), small[y + 1].tolist())
            ]
            rows.append("".join(cells) + RESET)
        blocks.append(rows)
    separator = " " * gap
    lines = []
    if titles is not None:
        lines.append(separator.join(title[:width].center(width) for title in titles))
    blank = " " * width
    for row in range(max((len(block) for block in blocks), default=0)):
        lines.append(separator.join(block[row] if row < len(block) else blank for block in blocks))
    return "\n".join(lines)


class TerminalOracle(Oracle):
    """Ask a person at a terminal, one query at a time, while training goes on.

    :meth:`~sb3_hhp.oracles.base.Oracle.submit` only enqueues. A daemon thread shows each query in turn: it writes the state and
    the two sub-goal images as PNG files into ``image_dir`` and prints their paths, prints a small
    colour preview of the three images side by side, and reads one line: ``1`` or ``left`` prefers
    the first sub-goal, ``2`` or ``right`` the second, ``=`` says both are equally good, ``x`` "can't
    tell" (INCOMPARABLE). Anything else re-prompts. :meth:`~sb3_hhp.oracles.base.Oracle.collect` returns the answers given so far.

    With ``reply_window_s`` set, a query left unanswered that long after it was shown is recorded as
    INCOMPARABLE (the paper's people had 5 seconds), and lines typed before a query appeared are not
    taken as its answer. Without it, the person takes as long as needed and lines are read in order
    (so a file of answers can be piped in). When the input ends, no more queries are shown: those left
    stay counted by :meth:`~sb3_hhp.oracles.base.Oracle.pending`, and ``input_closed`` becomes True.

    :param name: annotator name recorded with every answer
    :param input_stream: where replies are read, one per line (default: ``sys.stdin`` at construction)
    :param output_stream: where queries are shown (default: ``sys.stdout`` at construction)
    :param image_dir: folder for the PNG files; a temporary folder, removed by :meth:`~sb3_hhp.oracles.base.Oracle.close`, by default
    :param reply_window_s: seconds (> 0) a person has to reply to a shown query; None waits forever
    """

    #: columns per image in the colour preview
    preview_width: int = 24

    def __init__(
        self,
        name: str = "terminal",
        input_stream: Optional[TextIO] = None,
        output_stream: Optional[TextIO] = None,
        image_dir: Optional[str] = None,
        reply_window_s: Optional[float] = None,
    ) -> None:
        super().__init__(name)
        if reply_window_s is not None and not reply_window_s > 0:
            raise ValueError(f"reply_window_s must be > 0 seconds or None (no limit), got {reply_window_s}")
        self.input_stream = input_stream if input_stream is not None else sys.stdin
        self.output_stream = output_stream if output_stream is not None else sys.stdout
        self.reply_window_s = reply_window_s
        self._temporary_dir: Optional[tempfile.TemporaryDirectory] = None
        if image_dir is None:
            self._temporary_dir = tempfile.TemporaryDirectory(prefix="sb3_hhp_queries_")
            image_dir = self._temporary_dir.name
        os.makedirs(image_dir, exist_ok=True)
        self.image_dir = image_dir
        self.input_closed = False
        self._queries: queue.Queue[Optional[Query]] = queue.Queue()
        self._lines: queue.Queue[tuple[float, Optional[str]]] = queue.Queue()
        self._lock = threading.Lock()
        self._waiting = 0
        self._n_shown = 0
        self._closed = threading.Event()
        self._reader: Optional[threading.Thread] = None
        self._worker: Optional[threading.Thread] = None

    # --- the protocol -------------------------------------------------------------------------------

    def answer(self, query: Query) -> Label:
        raise NotImplementedError("TerminalOracle answers asynchronously: use submit() and collect()")

    def submit(self, queries: Sequence[Query]) -> None:
        if self._closed.is_set():
            raise RuntimeError("This TerminalOracle is closed")
        self._start()
        with self._lock:
            self._waiting += len(queries)
        for query in queries:
            self._queries.put(query)

    def collect(self) -> list[Answer]:
        with self._lock:
            return super().collect()

    def pending(self) -> int:
        with self._lock:
            return self._waiting

    def close(self) -> None:
        """Stop showing queries and remove the temporary image folder (if one was made)."""
        self._closed.set()
        self._queries.put(None)
        if self._worker is not None:
            self._worker.join(timeout=1.0)
        if self._temporary_dir is not None:
            self._temporary_dir.cleanup()
            self._temporary_dir = None

    # --- the threads --------------------------------------------------------------------------------

    def _start(self) -> None:
        if self._worker is None:
            self._reader = threading.Thread(target=self._read_lines, name=f"{self.name}-reader", daemon=True)
            self._worker = threading.Thread(target=self._ask_all, name=f"{self.name}-asker", daemon=True)
            self._reader.start()
            self._worker.start()

    def _read_lines(self) -> None:
        # a separate reader lets the asker wait for a reply with a time limit on any kind of stream
        while not self._closed.is_set():
            try:
                line = self.input_stream.readline()
            except (OSError, ValueError):  # closed stream
                line = ""
            self._lines.put((time.time(), line or None))
            if not line:
                return

    def _ask_all(self) -> None:
        while True:
            query = self._queries.get()
            if query is None or self._closed.is_set():
                return
            label = self._ask(query)
            if label is None:
                return
            with self._lock:
                self._ready.append(Answer(query.query_id, label, self.name))
                self._waiting -= 1

    def _ask(self, query: Query) -> Optional[Label]:
        """Show one query and read the reply; None when the input ended (or the oracle closed)."""
        self._show(query)
        shown_at = time.time()
        deadline = None if self.reply_window_s is None else shown_at + self.reply_window_s
        window = "" if self.reply_window_s is None else f" (within {self.reply_window_s:g} s)"
        while True:
            self._write(f"{PROMPT}{window}: ")
            reply = self._next_line(shown_at, deadline)
            if reply is _TIMED_OUT:
                self._write(f"\nNo reply within {self.reply_window_s:g} s: recorded as can't tell.\n")
                return Label.INCOMPARABLE
            if reply is None:
                self.input_closed = not self._closed.is_set()
                if self.input_closed:
                    self._write("\nInput closed: no more queries will be shown.\n")
                return None
            label = parse_reply(reply)
            if label is not None:
                return label
            self._write(f"Could not read {reply.strip()!r}: type 1 (or left), 2 (or right), = or x.\n")

    def _next_line(self, shown_at: float, deadline: Optional[float]) -> Union[str, None, object]:
        while not self._closed.is_set():
            timeout = 0.1 if deadline is None else min(0.1, deadline - time.time())
            if timeout <= 0:
                return _TIMED_OUT
            try:
                received_at, line = self._lines.get(timeout=timeout)
            except queue.Empty:
                continue
            if line is not None and deadline is not None and received_at < shown_at:
                continue  # typed before this query appeared: not an answer to it
            return line
        return None

    def _show(self, query: Query) -> None:
        self._n_shown += 1
        safe_id = re.sub(r"[^A-Za-z0-9_.-]", "_", str(query.query_id))
        lines = [f"\n=== Preference query {self._n_shown} (id {query.query_id}) ==="]
        shown = [
            ("state", "state", query.state_image),
            (f"sub-goal {query.goal1} (1, left)", "goal1", query.goal1_image),
            (f"sub-goal {query.goal2} (2, right)", "goal2", query.goal2_image),
        ]
        for title, tag, image in shown:
            if image is None:
                lines.append(f"{title}: no image")
                continue
            path = os.path.join(self.image_dir, f"{safe_id}_{tag}.png")
            cv2.imwrite(path, cv2.cvtColor(to_rgb_uint8(image), cv2.COLOR_RGB2BGR))
            lines.append(f"{title}: {path}")
        if any(image is not None for _, _, image in shown):
            titles = ["state", "1 (left)", "2 (right)"]
            lines.append(ansi_preview([image for _, _, image in shown], self.preview_width, titles))
        self._write("\n".join(lines) + "\n")

    def _write(self, text: str) -> None:
        encoding = getattr(self.output_stream, "encoding", None)
        if encoding:  # e.g. an ASCII terminal cannot print the half blocks
            text = text.encode(encoding, errors="replace").decode(encoding)
        try:
            self.output_stream.write(text)
            self.output_stream.flush()
        except (OSError, ValueError):  # the terminal went away: keep reading replies all the same
            pass


_TIMED_OUT = object()
