from esiaf import main
from esiaf_services.voiceid.service import VoiceId

raise SystemExit(main(VoiceId))
