from esiaf import main
from esiaf_services.wyoming.service import WyomingSource

raise SystemExit(main(WyomingSource))
