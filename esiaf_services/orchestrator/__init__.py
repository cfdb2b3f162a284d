"""ESIAF orchestrator: registration, heartbeats, results store, fusion, fused results API.

Run it with ``python -m esiaf_services.orchestrator``; build the app with :func:`create_app`.
"""
from .api.app import create_app
from .settings import OrchestratorSettings

__all__ = ["OrchestratorSettings", "create_app"]
