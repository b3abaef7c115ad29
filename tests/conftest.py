"""Shared test settings.

The networks in these tests are tiny (quick preset, 32 x 2); on a small shared machine intra-op threading
only adds contention (a 30-step run goes from ~0.05 s to >10 s), so torch runs single-threaded here.
"""

import torch

torch.set_num_threads(1)
