"""Number types shared by cellcal's pydantic models (the station set, the result, the
service's requests), in a module of their own: reading a station set does not load the
result's models (``calib.result``), which ``cellcal calibrate`` needs only once it has solved.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

#: A float that is neither NaN nor infinite (JSON has neither); every pydantic model of
#: cellcal that takes numbers takes these.
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
