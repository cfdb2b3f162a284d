from esiaf import main
from esiaf_services.splitter.service import Splitter

raise SystemExit(main(Splitter))
