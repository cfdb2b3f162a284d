from esiaf import main
from esiaf_services.gender.service import Gender

raise SystemExit(main(Gender))
