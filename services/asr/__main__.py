from esiaf import main
from services.asr.service import Asr

raise SystemExit(main(Asr))
