"""Hand-written reverse kernels (thesis eq 41-71): one reverse twin per forward kernel of mls_mpm."""
