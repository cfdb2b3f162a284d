from esiaf import main
from esiaf_services.beamformer.service import Beamformer

raise SystemExit(main(Beamformer))
