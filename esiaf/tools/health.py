"""A container's healthcheck: ``python -m esiaf.tools.health`` exits 0 when healthy, 1 (and one line) otherwise.

- A component (``ESIAF_HEALTH_FILE`` set, as in the images): healthy while the orchestrator has
  answered within ``--max-age`` seconds, i.e. it is registered and heartbeated (the control
  thread touches that file whenever the orchestrator answers; see esiaf/control.py).
- The orchestrator (``ESIAF_SERVICE=orchestrator``, as in its image): healthy when its own
  ``GET /health`` answers 200 on the port it listens on (``ESIAF_ORCHESTRATOR_PORT``, 8000).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import urllib.error
import urllib.request


def check_file(path: str, max_age_s: float) -> str | None:
    try:
        age = time.time() - os.stat(path).st_mtime
    except OSError:
        return f"unhealthy: {path} missing (not registered with the orchestrator yet)"
    if age > max_age_s:
        return f"unhealthy: the orchestrator has not answered for {age:.1f} s (> {max_age_s:g} s)"
    return None


def check_url(url: str, timeout_s: float) -> str | None:
    # urllib, not httpx: this runs every few seconds in every container, so it starts fast
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as response:
            status = response.status
    except urllib.error.HTTPError as exc:
        status = exc.code
    except (OSError, ValueError) as exc:
        return f"unhealthy: GET {url} failed: {exc}"
    if status != 200:
        return f"unhealthy: GET {url} answered {status}"
    return None


def main(argv: list[str] | None = None) -> int:
    env = os.environ
    parser = argparse.ArgumentParser(prog="python -m esiaf.tools.health", description=__doc__.splitlines()[0])
    parser.add_argument("--file", default=env.get("ESIAF_HEALTH_FILE", ""), help="health file of a component")
    parser.add_argument("--max-age", type=float, default=10.0, help="seconds (default 10)")
    parser.add_argument("--url", default="", help="HTTP URL to GET instead (default for the orchestrator: "
                                                  "its /health)")
    args = parser.parse_args(argv)
    url = args.url
    if not url and env.get("ESIAF_SERVICE") == "orchestrator":
        url = f"http://127.0.0.1:{env.get('ESIAF_ORCHESTRATOR_PORT', '8000')}/health"  # its own port, in its container
    if url:
        problem = check_url(url, timeout_s=2.0)
    elif args.file:
        problem = check_file(args.file, args.max_age)
    else:
        problem = "no health check: give --file, --url, or set ESIAF_HEALTH_FILE"
    if problem:
        print(problem, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
