"""The one HTTP client of the orchestrator's API, for components, the launcher and esiaf_services.

It carries the token on every request (``ESIAF_TOKEN``), keeps one connection pool, and retries
with exponential backoff (tenacity) what is worth retrying, for as long as the caller allows:

- the orchestrator unreachable (connection refused or reset, timeouts: it is starting or
  restarting);
- a 5xx answer (a database that cannot be written says 503);
- 409 with ``Retry-After``: an instance id still held by an instance that is not yet declared
  dead (a process restarted under its old id).

Anything else (2xx, 3xx, other 4xx) is returned at once: a refusal is not made better by asking
again.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any
from urllib.parse import quote

import httpx
import tenacity

from esiaf import auth

log = logging.getLogger(__name__)

BACKOFF_START_S = 0.1  # the first wait; it doubles with each attempt
BACKOFF_MAX_S = 2.0
ANNOUNCE_RETRY_S = 1.0  # a stream announcement is tried again this long while the orchestrator is away
TOPIC_POLL_S = 0.2  # declared_format asks this often for a producer of its topic
VOICES_MAX_WAIT_S = 60.0  # the longest long poll of GET /voices (wait_s)


def transient(response: httpx.Response) -> bool:
    """An answer that another attempt may change."""
    return response.status_code >= 500 or (response.status_code == 409 and "retry-after" in response.headers)


class OrchestratorHTTP:
    """``get``/``post``/``put``/``delete`` as httpx's (one attempt), and :meth:`request` with retries."""

    def __init__(self, url: str, timeout_s: float = 5.0) -> None:
        self.url = url.rstrip("/")
        self.attempts = 0  # of the last request()
        self._client = httpx.Client(base_url=self.url, timeout=timeout_s, headers=auth.headers(),
                                    verify=auth.tls_context() if self.url.startswith("https:") else True)

    def __enter__(self) -> OrchestratorHTTP:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._client.close()

    def get(self, path: str, **kwargs: Any) -> httpx.Response:
        return self._client.get(path, **kwargs)

    def post(self, path: str, **kwargs: Any) -> httpx.Response:
        return self._client.post(path, **kwargs)

    def put(self, path: str, **kwargs: Any) -> httpx.Response:
        return self._client.put(path, **kwargs)

    def delete(self, path: str, **kwargs: Any) -> httpx.Response:
        return self._client.delete(path, **kwargs)

    def request(self, method: str, path: str, *, retry_for_s: float = 0.0,
                stopping: Callable[[], bool] = lambda: False,
                on_retry: Callable[[str], None] | None = None, **kwargs: Any) -> httpx.Response:
        """One request, tried again while it fails transiently (see the module) and the next wait
        still ends within ``retry_for_s`` and ``stopping()`` is false. Returns the last answer, or
        raises the last ``httpx.HTTPError`` if no attempt got one. ``on_retry(why)`` is called
        before each wait."""
        self.attempts = 0

        def attempt() -> httpx.Response:
            self.attempts += 1
            return self._client.request(method, path, **kwargs)

        def before_sleep(state: tenacity.RetryCallState) -> None:
            if on_retry is not None and state.outcome is not None:
                failed = state.outcome.exception()
                on_retry(str(failed) or type(failed).__name__ if failed is not None
                         else why(state.outcome.result()))

        retrying = tenacity.Retrying(
            stop=tenacity.stop_before_delay(retry_for_s) | _StopWhen(stopping),
            wait=tenacity.wait_exponential(multiplier=BACKOFF_START_S, min=BACKOFF_START_S, max=BACKOFF_MAX_S),
            retry=tenacity.retry_if_exception_type(httpx.TransportError) | tenacity.retry_if_result(transient),
            before_sleep=before_sleep,
            # out of time: the last answer as it is, or its transport error raised
            retry_error_callback=lambda state: state.outcome.result() if state.outcome is not None else None)
        return retrying(attempt)


def why(response: httpx.Response) -> str:
    """What an error answer says: its ``detail`` (pydantic's list made one line), else its text."""
    try:
        detail = response.json().get("detail", response.text)
    except (ValueError, AttributeError):
        detail = response.text
    if isinstance(detail, list):  # pydantic validation errors
        detail = "; ".join(f"{'.'.join(str(p) for p in d.get('loc', []))}: {d.get('msg')}" for d in detail)
    return f"HTTP {response.status_code}: {detail}" if response.status_code >= 500 else str(detail)


class _StopWhen(tenacity.stop.stop_base):
    """Stops retrying once ``stopping()`` says so (the component is shutting down)."""

    def __init__(self, stopping: Callable[[], bool]) -> None:
        self._stopping = stopping

    def __call__(self, retry_state: tenacity.RetryCallState) -> bool:
        return self._stopping()


def announce_stream(url: str, stream_id: str, start_ns: int, source: str, info: dict[str, Any]) -> bool:
    """Tells the orchestrator a stream's capture started (``PUT /streams/{id}``); False if it could not
    (tried again for a few seconds while the orchestrator is unreachable)."""
    try:
        with OrchestratorHTTP(url) as http:
            response = http.request("PUT", f"/streams/{quote(stream_id, safe='')}", retry_for_s=ANNOUNCE_RETRY_S,
                                    json={"start_ns": start_ns, "source": source, "info": info})
        response.raise_for_status()
    except httpx.HTTPError as exc:
        log.warning("could not announce stream_id=%s start_ns=%d error=%s", stream_id, start_ns, exc)
        return False
    return True


def declared_format(url: str, topic: str, timeout_s: float,
                    stopping: Callable[[], bool] = lambda: False) -> dict[str, Any] | None:
    """The format a producer of ``topic`` declared (``GET /topics``), waiting up to ``timeout_s`` for
    one to register; None if none did. For components that take whatever a topic carries."""
    def producers() -> list[dict[str, Any]]:
        try:
            items = http.get("/topics").json()["items"]
        except (httpx.HTTPError, ValueError, KeyError) as exc:
            log.info("waiting for orchestrator url=%s error=%s", url, exc)
            return []
        return next((t["producers"] for t in items if t["topic"] == topic), [])

    with OrchestratorHTTP(url) as http:
        found = tenacity.Retrying(stop=tenacity.stop_after_delay(timeout_s), wait=tenacity.wait_fixed(TOPIC_POLL_S),
                                  retry=tenacity.retry_if_result(lambda found: not found and not stopping()),
                                  retry_error_callback=lambda state: None)(producers)
    return found[0]["format"] if found else None
