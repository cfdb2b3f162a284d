from esiaf import main
from esiaf_services.grabber.service import Grabber

raise SystemExit(main(Grabber))
