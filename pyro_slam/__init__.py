"""pyro_slam: DVBF-LM (Mirchev et al., RSS 2019) and PF-net in Pyro."""

import os

# OpenMP threads that wait sleep instead of spinning (see pyro_slam.runtime); only effective
# when pyro_slam is imported before torch, and never over the environment's own choice
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
