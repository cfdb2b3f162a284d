from esiaf import main
from esiaf_services.ssl.service import Ssl

raise SystemExit(main(Ssl))
