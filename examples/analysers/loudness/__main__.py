"""``python examples/analysers/loudness`` or ``esiaf run --with examples/analysers/loudness``."""
from loudness import Loudness

from esiaf import main

raise SystemExit(main(Loudness))
