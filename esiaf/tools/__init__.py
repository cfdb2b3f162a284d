"""The tools around the SDK: the launcher and the `esiaf` command, the evaluation harness, the testing kit
and the container healthcheck. A component needs none of them (it imports from :mod:`esiaf`)."""
