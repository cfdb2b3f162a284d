"""The wyoming service's settings: where it listens, what describe says, and what a peer may send."""
from __future__ import annotations

from pydantic import Field

from esiaf.settings import ComponentSettings


class WyomingSettings(ComponentSettings):
    listen_host: str = "127.0.0.1"  # where the Wyoming server listens (0.0.0.0: every interface)
    port: int = Field(default=10300, ge=1, le=65535)  # the Wyoming server's TCP port
    topic: str = "wyoming/audio"  # where the sessions' audio is published (what esiaf wyoming's vad hears)
    # the vad's speech, whose starts and ends are sent as voice-started / voice-stopped to the sessions that ask
    # for them; "" hears none
    speech_topic: str = "vad/speech"
    model: str = "pocketsphinx"  # the recogniser, as `describe` names it
    model_description: str = ""  # ... and what it recognises (a grammar)
    languages: list[str] = Field(default_factory=lambda: ["en"])  # the recogniser's, as `describe` lists them
    # transcript-start / transcript-chunk / transcript-stop while the client speaks, from the recogniser's
    # partial results (their stable words only: a chunk is never taken back); false: the transcript alone
    stream_transcripts: bool = True
    max_sessions: int = Field(default=32, ge=1)  # connections served at once; more get an error event
    max_chunk_bytes: int = Field(default=1 << 20, ge=1024)  # an event's payload (an audio chunk) at most
    max_data_bytes: int = Field(default=64 << 10, ge=1024)  # an event's JSON data at most
    max_session_s: float = Field(default=120.0, gt=0)  # audio of one audio-start ... audio-stop at most
    # a session with audio started that sends nothing for this long: its stream ends, it gets an error
    idle_timeout_s: float = Field(default=10.0, gt=0)
    connection_idle_s: float = Field(default=60.0, gt=0)  # a connection without a session: closed after this
    transcript_timeout_s: float = Field(default=30.0, gt=0)  # after audio-stop: the stream's end at most this late
    wait_for_subscribers: int = Field(default=1, ge=0)  # before listening, wait until the topic has these
    wait_timeout_s: float = Field(default=60.0, gt=0)  # ... at most this long, then it listens anyway
