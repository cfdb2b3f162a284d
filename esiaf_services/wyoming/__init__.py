"""Wyoming service: ESIAF as a Wyoming speech-to-text server (Home Assistant's voice pipelines)."""
