from esiaf import main
from esiaf_services.asr.service import Asr

raise SystemExit(main(Asr))
