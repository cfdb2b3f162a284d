from esiaf import main
from services.splitter.service import Splitter

raise SystemExit(main(Splitter))
