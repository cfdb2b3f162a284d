"""What ``esiaf run`` answers with one line on stderr and exit code 2. Apart from the launcher, so
that the command line is checked before the heavy modules are imported."""


class LaunchError(Exception):
    """A bad option or setting, or a service that did not come up; the message says which and why."""
