from esiaf import main
from esiaf_services.denoiser.service import Denoiser

raise SystemExit(main(Denoiser))
