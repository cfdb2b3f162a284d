from esiaf import main
from esiaf_services.player.service import Player

raise SystemExit(main(Player))
