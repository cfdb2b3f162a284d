"""Speech building blocks the services share, so that no service imports another: the segmenter
and its windows (the vad service's, which the utterance analysers use to find the same speech span),
the Silero VAD model, openSMILE features of an utterance, and the label classifiers (ONNX over
those features, or a class of your own) that the emotion and gender services load.

Each module imports its heavy library (onnxruntime, openSMILE's binding) only when it is used.
"""
