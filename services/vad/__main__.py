from esiaf import main
from services.vad.service import Vad

raise SystemExit(main(Vad))
