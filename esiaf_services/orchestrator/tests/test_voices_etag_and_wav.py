"""The voices' ETag never repeats (a voice deleted and another enrolled in its place, a restart), and
a WAV whose header is cut short or names 0 channels or 0 bits per sample is a 422 on a connection
that goes on: the orchestrator as a process, real enrolments, a raw HTTP connection."""
from __future__ import annotations

import socket

import pytest

from bench.bad_cli import wav_header
from esiaf.tools.testing import Orchestrator, shared_data


@pytest.fixture
def orchestrator(tmp_path):
    running = Orchestrator(tmp_path)
    yield running
    running.close()


def enrol(orchestrator: Orchestrator, name: str) -> None:
    wav = shared_data("speech/cmu_arctic/cmu_arctic_us_aew_a0001.wav").read_bytes()
    reply = orchestrator.http.post(f"/voices/{name}", files={"audio": ("a.wav", wav)}, timeout=60)
    assert reply.status_code == 200, reply.text


def etag(orchestrator: Orchestrator) -> str:
    return orchestrator.http.get("/voices", params={"embeddings": 1}).headers["ETag"]


def test_a_voice_deleted_and_another_enrolled_in_its_place_changes_the_etag_for_good(orchestrator):
    enrol(orchestrator, "Anna")
    enrol(orchestrator, "Ben")
    seen = [etag(orchestrator)]
    assert orchestrator.http.delete("/voices/Ben").status_code == 200
    seen.append(etag(orchestrator))
    enrol(orchestrator, "Cleo")  # takes Ben's row id: as many rows, the same largest id as before
    seen.append(etag(orchestrator))
    assert len(set(seen)) == 3, seen
    orchestrator.kill()
    orchestrator.start()  # the generation is kept in the database
    assert etag(orchestrator) == seen[-1]
    assert orchestrator.http.delete("/voices/Cleo").status_code == 200
    assert etag(orchestrator) not in seen


@pytest.mark.parametrize("audio", [wav_header(16000)[:30], wav_header(16000, channels=0), wav_header(16000, bits=0)],
                         ids=["30 bytes", "0 channels", "0 bits"])
def test_a_broken_wav_header_is_a_422_and_the_connection_goes_on(orchestrator, audio):
    boundary = b"esiafboundary"
    body = (b"--" + boundary + b'\r\nContent-Disposition: form-data; name="audio"; filename="a.wav"\r\n'
            b"Content-Type: audio/wav\r\n\r\n" + audio + b"\r\n--" + boundary + b"--\r\n")
    post = (b"POST /voices/Anna HTTP/1.1\r\nHost: esiaf\r\nContent-Type: multipart/form-data; boundary=" + boundary
            + b"\r\nContent-Length: %d\r\n\r\n" % len(body) + body)
    with socket.create_connection(("127.0.0.1", orchestrator.port), timeout=60) as sock:
        sock.sendall(post)
        first = response(sock)
        assert first.startswith(b"HTTP/1.1 422"), first
        assert b"not a readable WAV file" in first
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: esiaf\r\n\r\n")  # the same connection
        assert response(sock).startswith(b"HTTP/1.1 200")


def response(sock: socket.socket) -> bytes:
    """One HTTP response read whole from ``sock``: its headers, and as many bytes as their Content-Length."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"the connection was closed after {data!r}"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = int(next(line.split(b":")[1] for line in head.split(b"\r\n")
                      if line.lower().startswith(b"content-length")))
    while len(body) < length:
        chunk = sock.recv(65536)
        assert chunk, f"the connection was closed after {data!r}"
        body += chunk
    return head + b"\r\n\r\n" + body
