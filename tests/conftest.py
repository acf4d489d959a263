"""Test-session settings."""
import torch

# The tests run many small tensor ops (the walk on small frames): one thread is faster than two,
# and it keeps subprocess tests (DDP, kill-and-resume) from oversubscribing a 2-core machine.
torch.set_num_threads(1)
