"""`python -m esiaf ...` is the `esiaf` command (esiaf.tools.cli)."""
from esiaf.tools.cli import main

raise SystemExit(main())
