from esiaf import main
from services.grabber.service import Grabber

raise SystemExit(main(Grabber))
