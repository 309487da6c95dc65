"""Plant models: the nonlinear dq model (``dqmodel``), the 2008 transfer
function (``tfmodel``), the TS fuzzy models (``tsfuzzy``) and the six-step
drive simulations (``simulate``).  Imports nothing of picdrive above the core
(profile, control law)."""
