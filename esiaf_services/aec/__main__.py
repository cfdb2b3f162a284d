from esiaf import main
from esiaf_services.aec.service import EchoCanceller

raise SystemExit(main(EchoCanceller))
