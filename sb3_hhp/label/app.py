"""The labeling web application: people compare two sub-goals in a state (section 4.1.1).

The page (``/``) shows the current state and the two sub-goal images side by side and takes
FIRST / SECOND / EQUAL / CAN'T TELL by button or key (Left, Right, ``=``, ``x``) within a reply
window (5 s, as the paper's annotators had); when the window runs out the page answers CAN'T TELL.
Several annotators may label at once: a question handed to one is leased to them for the reply
window plus a grace period, so two people are not shown the same question at the same time.
``/gallery`` shows every sub-goal with its statistics and refreshes itself.

JSON API (all under ``/api``; with a token, pass it as ``X-Token`` header, ``Authorization: Bearer``
or ``?token=``):

- ``GET /api/next?annotator=NAME``: the next open question for NAME (``query`` is ``null`` if none)
- ``POST /api/answer`` ``{"query_id", "label", "annotator"}``: 404 unknown id, 409 answered already,
  422 bad label or missing annotator; the store is unchanged on any error
- ``GET /api/stats``: queue length and answer counts
- ``GET /api/image/{query_id}/{which}.png``: ``which`` in state/goal1/goal2, only for open queries
- ``GET /api/subgoals``, ``GET /api/subgoal/{id}.png``: the sub-goal gallery
"""

import secrets
import threading
import time
from pathlib import Path
from typing import Any, Optional

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from sb3_hhp.oracles.base import Label
from sb3_hhp.preferences.store import IMAGE_KINDS, AlreadyAnswered, PreferenceStore

__all__ = ["LEASE_GRACE_S", "create_app"]

STATIC_DIR = Path(__file__).resolve().parent / "static"
#: seconds a question stays leased to its annotator after the reply window ran out
LEASE_GRACE_S = 5.0
_NO_STORE = {"Cache-Control": "no-store"}


class AnswerIn(BaseModel):
    """The body of ``POST /api/answer``."""

    query_id: str = Field(min_length=1)
    label: Any
    annotator: str = Field(min_length=1, max_length=100)


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

    app = FastAPI(title="sb3_hhp labeling", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.store = store
    app.state.reply_window_s = reply_window_s
    api = APIRouter(prefix="/api", dependencies=[Depends(check_token)])

    def counts(annotator: Optional[str] = None) -> dict:
        stats = store.stats()
        result = {"queued": stats["queued"], "answered": stats["answered"], "per_annotator": stats["per_annotator"]}
        if annotator is not None:
            result["answered_by_you"] = stats["per_annotator"].get(annotator, 0)
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
                query = store.get_query(query_id)
                kinds = store.image_kinds(query_id)
            except KeyError:  # pragma: no cover - queries are never deleted
                query = None
            if query is not None:
                question = {
                    "query_id": query.query_id,
                    "goal1": query.goal1,
                    "goal2": query.goal2,
                    "asked_at": query.asked_at,
                    "images": {
                        kind: (f"/api/image/{query.query_id}/{kind}.png" if kind in kinds else None)
                        for kind in IMAGE_KINDS
                    },
                }
        return {"query": question, "reply_window_s": reply_window_s, **counts(annotator)}

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
            answer = store.add_answer(body.query_id, label, annotator)
        except KeyError as error:
            raise HTTPException(status_code=404, detail=f"Unknown query id {body.query_id!r}") from error
        except AlreadyAnswered as error:
            raise HTTPException(status_code=409, detail=str(error)) from error
        except ValueError as error:
            raise HTTPException(status_code=422, detail=str(error)) from error
        leases.release(body.query_id)
        return {
            "query_id": answer.query_id,
            "label": answer.label.name,
            "annotator": answer.annotator,
            "answered_at": answer.answered_at,
            **counts(annotator),
        }

    @api.get("/stats")
    def stats() -> dict:
        return {**store.stats(), "reply_window_s": reply_window_s}

    @api.get("/image/{query_id}/{which}.png")
    def image(query_id: str, which: str) -> Response:
        # Only questions still open are shown: answered ones are nobody's business any more.
        if which not in IMAGE_KINDS or not store.is_open(query_id):
            raise HTTPException(status_code=404, detail="No such image of an open question")
        try:
            png = store.image_png(query_id, which)
        except KeyError as error:
            raise HTTPException(status_code=404, detail="No such image of an open question") from error
        return Response(content=png, media_type="image/png", headers=_NO_STORE)

    @api.get("/subgoals")
    def subgoals() -> dict:
        records = store.subgoals(with_images=False)
        for record in records:
            record["image"] = f"/api/subgoal/{record['id']}.png"
        return {"subgoals": records, "time": time.time()}

    @api.get("/subgoal/{subgoal_id}.png")
    def subgoal_image(subgoal_id: int) -> Response:
        try:
            png = store.subgoal_png(subgoal_id)
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
