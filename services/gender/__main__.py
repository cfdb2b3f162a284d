from esiaf import main
from services.gender.service import Gender

raise SystemExit(main(Gender))
