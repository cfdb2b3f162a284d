from esiaf import main
from services.emotion.service import Emotion

raise SystemExit(main(Emotion))
