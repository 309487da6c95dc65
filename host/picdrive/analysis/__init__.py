"""Analysis on the models: step metrics (``metrics``), H2/H-inf norms and
sampled loops (``h2hinf``).  Imports models and the core only."""
