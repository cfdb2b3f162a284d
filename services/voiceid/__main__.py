from esiaf import main
from services.voiceid.service import VoiceId

raise SystemExit(main(VoiceId))
