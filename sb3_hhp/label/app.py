"""The labeling web application: people compare two sub-goals in a state (section 4.1.1).

The page (``/``) shows the first sub-goal on the left, the current state in the middle and the
second sub-goal on the right, each sub-goal named in words, and takes FIRST / SECOND / EQUAL /
CAN'T TELL by button or key (Left = left image, Right = right image, ``=``, ``x``) within a reply
window (5 s, as the paper's annotators had); when the window runs out the page answers CAN'T TELL.
Where the goal space can draw from the state's privileged facts (MiniGrid), each sub-goal is drawn
in the current state's room with the cells it concerns highlighted, and the image from where it was
found is one key (``e``) away. Several annotators may label at once: a question handed to one is
leased to them for the reply window plus a grace period, so two people are not shown the same
question at the same time. ``/gallery`` shows every sub-goal with its statistics and refreshes itself.

JSON API (all under ``/api``; with a token, pass it as ``X-Token`` header, ``Authorization: Bearer``
or ``?token=``):

- ``GET /api/next?annotator=NAME``: the next open question for NAME (``query`` is ``null`` if none),
  with the counts the page shows (budget, waiting, distinct questions, NAME's answers and median time)
- ``POST /api/answer`` ``{"query_id", "label", "annotator", "response_s", "next"}``: 404 unknown id,
  409 answered already, 422 bad label, missing annotator or bad ``response_s`` (seconds the person
  took); with ``"next": true`` the reply holds the annotator's next question as ``next``
- ``GET /api/stats``: queue length and answer counts
- ``GET /api/image/{query_id}/{which}.png``: ``which`` in :data:`IMAGE_NAMES`, only for open queries
- ``GET /api/subgoals``, ``GET /api/subgoal/{id}.png``: the sub-goal gallery

Bad input never reaches the store: bodies above :data:`MAX_BODY_BYTES` get 413, ids longer than
:data:`MAX_ID_LENGTH` or out of SQLite's range and any malformed parameter get 4xx, and error
messages do not echo what was sent.
"""

import functools
import secrets
import statistics
import threading
import time
from pathlib import Path
from typing import Any, Optional

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from sb3_hhp.goals.base import GoalSpace
from sb3_hhp.preferences.codecs import encode_png
from sb3_hhp.preferences.store import IMAGE_KINDS, AlreadyAnswered, PreferenceStore
from sb3_hhp.preferences.types import Label
from sb3_hhp.subgoal_table import MAX_SUBGOAL_ID, SubgoalTable

__all__ = ["IMAGE_NAMES", "LEASE_GRACE_S", "MAX_BODY_BYTES", "MAX_ID_LENGTH", "create_app"]

STATIC_DIR = Path(__file__).resolve().parent / "static"
#: seconds a question stays leased to its annotator after the reply window ran out
LEASE_GRACE_S = 5.0
#: the largest request body accepted (an answer is about 100 bytes); larger ones get 413
MAX_BODY_BYTES = 16 * 1024
#: the longest query id accepted (training writes 32 hex digits)
MAX_ID_LENGTH = 200
#: the images of a question: state, the two sub-goals (drawn in the state's layout when the goal
#: space can, else the images where they were found) and, when drawn, the images where they were found
IMAGE_NAMES = ("state", "goal1", "goal2", "goal1_found", "goal2_found")
#: pixels per MiniGrid cell of the images drawn from a state's privileged facts
LAYOUT_TILE = 32
_NO_STORE = {"Cache-Control": "no-store"}
_IMAGE_CACHE_SIZE = 256


class AnswerIn(BaseModel):
    """The body of ``POST /api/answer``."""

    query_id: str = Field(min_length=1, max_length=MAX_ID_LENGTH)
    label: Any
    annotator: str = Field(min_length=1, max_length=100)
    #: seconds from the question shown to the answer, as the page measured them
    response_s: Optional[float] = Field(default=None, ge=0, le=3600)
    #: hand the annotator their next question in the reply (saves the page a round trip)
    next: bool = False


def layout_goal_space(info: dict) -> Optional[GoalSpace]:
    """The goal space that draws a question in its state's layout, from what its ``info`` holds (None: none can).

    MiniGrid questions carry the state's grid (``info["state"]["grid"]``) and the sub-goal keys
    (``goal1_key``): 5 numbers with colours (the second :data:`~sb3_hhp.goals.minigrid.RELATIVE` where they say how
    colours relate), 3 without (one more where it faces an open door and the goal space counts open doors).
    """
    state, key = info.get("state"), info.get("goal1_key")
    if not isinstance(state, dict) or "grid" not in state or not isinstance(key, list):
        return None
    from sb3_hhp.goals.minigrid import RELATIVE, MiniGridGoalSpace

    colored = len(key) in (5, 6)
    return MiniGridGoalSpace(use_color="relative" if colored and key[1] == RELATIVE else colored, tile_size=LAYOUT_TILE)


def draw_question(info: dict) -> dict[str, bytes]:
    """PNGs of a question drawn in its state's layout: ``state``, ``goal1``, ``goal2`` (empty when the goal
    space cannot draw it, or the facts are malformed: people then see the stored images)."""
    goal_space = layout_goal_space(info)
    if goal_space is None:
        return {}
    state = info["state"]
    try:
        images = {
            "state": goal_space.image_in_state(state),
            "goal1": goal_space.image_in_state(state, goal_space.key_from_json(info["goal1_key"])),
            "goal2": goal_space.image_in_state(state, goal_space.key_from_json(info["goal2_key"])),
        }
    except (KeyError, TypeError, ValueError, IndexError):
        return {}
    if any(image is None for image in images.values()):
        return {}
    return {kind: encode_png(image, f"the {kind} drawn in the state's layout") for kind, image in images.items()}


class _Leases:
    """Which annotator holds which open question, until when (in-process, thread-safe)."""

    def __init__(self, duration_s: float) -> None:
        self.duration_s = duration_s
        self._lock = threading.Lock()
        self._held: dict[str, tuple[str, float]] = {}

    def pick(self, open_ids: list[str], annotator: str) -> Optional[str]:
        """The oldest open question free for ``annotator`` (one they hold first), leased to them."""
        now = time.monotonic()
        with self._lock:
            open_set = set(open_ids)
            self._held = {qid: held for qid, held in self._held.items() if held[1] > now and qid in open_set}
            chosen = next((qid for qid in open_ids if self._held.get(qid, ("",))[0] == annotator), None)
            if chosen is None:
                chosen = next((qid for qid in open_ids if qid not in self._held), None)
            if chosen is not None:
                self._held[chosen] = (annotator, now + self.duration_s)
            return chosen

    def release(self, query_id: str) -> None:
        with self._lock:
            self._held.pop(query_id, None)


def create_app(store: PreferenceStore, token: Optional[str] = None, reply_window_s: float = 5.0) -> "FastAPI":
    """Build the labeling application over ``store``.

    :param store: the preference store whose open queries are shown and where answers are written
    :param token: when given, every ``/api`` call must carry it (header ``X-Token``,
        ``Authorization: Bearer <token>`` or query parameter ``token``), else 401
    :param reply_window_s: seconds an annotator has per question before the page answers
        CAN'T TELL (> 0; the paper's annotators had 5 s)
    :return: the FastAPI application (serve it with uvicorn, or use :class:`~sb3_hhp.label.server.LabelServer`)
    """
    if not isinstance(store, PreferenceStore):
        raise ValueError(f"create_app needs a PreferenceStore, got {type(store).__name__}")
    if token is not None and (not isinstance(token, str) or not token):
        raise ValueError("token must be a non-empty string or None")
    if not reply_window_s > 0:
        raise ValueError(f"reply_window_s must be > 0 seconds, got {reply_window_s}")
    reply_window_s = float(reply_window_s)
    leases = _Leases(reply_window_s + LEASE_GRACE_S)

    def check_token(request: Request) -> None:
        if token is None:
            return
        given = request.headers.get("x-token") or request.query_params.get("token") or ""
        authorization = request.headers.get("authorization", "")
        if not given and authorization.lower().startswith("bearer "):
            given = authorization[7:].strip()
        if not secrets.compare_digest(given.encode(), token.encode()):
            raise HTTPException(
                status_code=401,
                detail="Missing or wrong token: open the page as /?token=<token> or send the X-Token header",
                headers={"WWW-Authenticate": "Bearer"},
            )

    app = FastAPI(
        title="sb3_hhp labeling", docs_url=None, redoc_url=None, openapi_url=None, max_body_size=MAX_BODY_BYTES
    )
    app.state.store = store
    subgoal_table = SubgoalTable(store)
    app.state.reply_window_s = reply_window_s
    api = APIRouter(prefix="/api", dependencies=[Depends(check_token)])

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, error: RequestValidationError) -> JSONResponse:
        # Say which field is wrong and why, without echoing what was sent (it may be megabytes).
        problems = [
            f"{'.'.join(str(part) for part in problem.get('loc', ()))}: {problem.get('msg', 'invalid')}"
            for problem in error.errors()
        ]
        return JSONResponse(status_code=422, content={"detail": problems})

    @functools.lru_cache(maxsize=_IMAGE_CACHE_SIZE)
    def drawn(query_id: str) -> dict[str, bytes]:
        return draw_question(store.query_info(query_id))

    def counts(annotator: Optional[str] = None) -> dict:
        stats = store.stats()
        result = {
            key: stats[key] for key in ("asked", "budget", "queued", "answered", "distinct", "signed", "per_annotator")
        }
        if annotator is not None:
            result["answered_by_you"] = stats["per_annotator"].get(annotator, 0)
            times = store.response_times(annotator)
            result["your_median_s"] = statistics.median(times) if times else None
        return result

    @api.get("/next")
    def next_question(annotator: str = Query(min_length=1, max_length=100)) -> dict:
        annotator = annotator.strip()
        if not annotator:
            raise HTTPException(status_code=422, detail="annotator must not be blank")
        query_id = leases.pick(store.open_query_ids(), annotator)
        question = None
        if query_id is not None:
            try:
                question = describe_question(query_id)
            except KeyError:  # pragma: no cover - queries are never deleted
                question = None
        return {"query": question, "reply_window_s": reply_window_s, **counts(annotator)}

    def describe_question(query_id: str) -> dict:
        info = store.query_info(query_id)
        goals = store.query_goals(query_id)
        kinds = set(store.image_kinds(query_id))
        layout = drawn(query_id)
        images: dict[str, Optional[str]] = {}
        for kind in IMAGE_KINDS:
            images[kind] = f"/api/image/{query_id}/{kind}.png" if kind in kinds or kind in layout else None
            if kind != "state":
                found = kind in layout and kind in kinds
                images[f"{kind}_found"] = f"/api/image/{query_id}/{kind}_found.png" if found else None
        return {
            "query_id": query_id,
            "goal1": goals[0],
            "goal2": goals[1],
            "goal1_name": str(info.get("goal1_name") or f"sub-goal #{goals[0]}"),
            "goal2_name": str(info.get("goal2_name") or f"sub-goal #{goals[1]}"),
            "drawn_in_state": bool(layout),
            "asked_at": goals[2],
            "images": images,
        }

    @api.post("/answer")
    def post_answer(body: AnswerIn) -> dict:
        annotator = body.annotator.strip()
        if not annotator:
            raise HTTPException(status_code=422, detail="annotator must not be blank")
        try:
            label = Label.parse(body.label)
        except ValueError as error:
            raise HTTPException(status_code=422, detail=str(error)) from error
        try:
            answer = store.add_answer(body.query_id, label, annotator, response_s=body.response_s)
        except KeyError as error:
            raise HTTPException(status_code=404, detail=f"Unknown query id {body.query_id!r}") from error
        except AlreadyAnswered as error:
            raise HTTPException(status_code=409, detail=str(error)) from error
        except ValueError as error:
            raise HTTPException(status_code=422, detail=str(error)) from error
        leases.release(body.query_id)
        reply = {
            "query_id": answer.query_id,
            "label": answer.label.name,
            "annotator": answer.annotator,
            "answered_at": answer.answered_at,
            **counts(annotator),
        }
        if body.next:
            next_id = leases.pick(store.open_query_ids(), annotator)
            reply["next"] = None if next_id is None else describe_question(next_id)
        return reply

    @api.get("/stats")
    def stats() -> dict:
        return {**store.stats(), "reply_window_s": reply_window_s}

    @api.get("/image/{query_id}/{which}.png")
    def image(query_id: str = PathParam(max_length=MAX_ID_LENGTH), which: str = PathParam(max_length=20)) -> Response:
        # Only questions still open are shown: answered ones are nobody's business any more.
        if which not in IMAGE_NAMES or not store.is_open(query_id):
            raise HTTPException(status_code=404, detail=f"No such image of an open question; images: {IMAGE_NAMES}")
        try:
            if which.endswith("_found"):  # the image where the sub-goal was found
                png = store.image_png(query_id, which[: -len("_found")])
            else:  # drawn in the state's layout when the goal space can, else the stored image
                png = drawn(query_id).get(which) or store.image_png(query_id, which)
        except KeyError as error:
            raise HTTPException(status_code=404, detail="No such image of an open question") from error
        return Response(content=png, media_type="image/png", headers=_NO_STORE)

    @api.get("/subgoals")
    def subgoals() -> dict:
        records = subgoal_table.records(with_images=False)
        for record in records:
            record["image"] = f"/api/subgoal/{record['id']}.png"
        return {"subgoals": records, "time": time.time()}

    @api.get("/subgoal/{subgoal_id}.png")
    def subgoal_image(subgoal_id: int = PathParam(ge=0, le=MAX_SUBGOAL_ID)) -> Response:
        try:
            png = subgoal_table.png(subgoal_id)
        except KeyError as error:
            raise HTTPException(status_code=404, detail=f"Unknown sub-goal id {subgoal_id}") from error
        return Response(content=png, media_type="image/png", headers=_NO_STORE)

    app.include_router(api)

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", headers=_NO_STORE)

    @app.get("/gallery", include_in_schema=False)
    def gallery() -> FileResponse:
        return FileResponse(STATIC_DIR / "gallery.html", headers=_NO_STORE)

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    return app
