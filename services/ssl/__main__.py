from esiaf import main
from services.ssl.service import Ssl

raise SystemExit(main(Ssl))
