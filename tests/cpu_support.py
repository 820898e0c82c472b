"""Marks for tests that need a CPU feature: they skip, with the reason, on a CPU without it."""

import pytest

from common.cpu_capability import bfloat16_problem

needs_bfloat16 = pytest.mark.skipif(bfloat16_problem() is not None,
                                    reason=f"bfloat16 cannot run on this CPU: {bfloat16_problem()}")
