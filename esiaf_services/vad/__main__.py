from esiaf import main
from esiaf_services.vad.service import Vad

raise SystemExit(main(Vad))
