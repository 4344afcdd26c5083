"""Hierarchical Locomotion Model (Pan & Torresani, ICML 2009): variational-EM training
(``hlm.train``), offline smoothing/Viterbi/fill (``hlm.offline``), the online forward filter
(``hlm.online``) and the model behind the Filler seam (``hlm.model``)."""
