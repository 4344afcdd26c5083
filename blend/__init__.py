"""The recommended causal filler, ``default``: hold, damped velocity and a conditional-Gaussian
regression on the observed channels, anchored at the last observed value and stacked with
weights chosen on the validation split (see blend.model)."""
