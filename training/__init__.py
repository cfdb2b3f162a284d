"""Training the models the project bundles, from data it has: the emotion and gender classifiers on
Berlin EmoDB (:mod:`training.emodb`, which writes each into its service's ``models/`` folder, and the
model card, :mod:`training.model_card`). A repository tool like ``bench/``: no service imports it.
"""
