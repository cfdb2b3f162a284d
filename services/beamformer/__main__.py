from esiaf import main
from services.beamformer.service import Beamformer

raise SystemExit(main(Beamformer))
