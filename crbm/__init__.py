"""Conditional RBM (Taylor, Hinton & Roweis 2006) for motion: CD-1 training (``crbm.model``),
the online clamped-Gibbs filler behind the Filler seam (``crbm.filler``), generation
(``crbm.generate``), the second level of section 6 (``levels=2``), model files
(``crbm.persist``), the registered methods ``crbm``, ``crbm-mf``, ``crbm-2level``, ``crbm-imp``,
``crbm-ens`` (``crbm.methods``; the pooled-chain ensemble is ``crbm.ensemble``) and ``lacuna train|generate crbm`` (``crbm.cli``)."""
