from esiaf import main
from esiaf_services.emotion.service import Emotion

raise SystemExit(main(Emotion))
