"""Contact laws: what a bounce does to a ball, one law per file under one abstract base.

``_base.py`` says what a law is (:class:`AbstractContactLaw`, :class:`AbstractSeriesLaw`,
:class:`AbstractSummableLaw`);
``_factor.py`` is the seed's law (:class:`FactorLaw`), ``_friction.py`` a bounce that
depends on spin (:class:`FrictionLaw`); ``law_of(scene)`` gives the law a
scene's contacts follow (``Scene.law``, the factor law by default).
"""

from ._base import AbstractContactLaw as AbstractContactLaw
from ._base import AbstractSeriesLaw as AbstractSeriesLaw
from ._base import AbstractSummableLaw as AbstractSummableLaw
from ._base import Series as Series
from ._base import series as series
from ._default import law_of as law_of
from ._default import laws_reading as laws_reading
from ._factor import FactorCoefficients as FactorCoefficients
from ._factor import FactorLaw as FactorLaw
from ._friction import FrictionCoefficients as FrictionCoefficients
from ._friction import FrictionLaw as FrictionLaw
from ._geometric import geometric_count as geometric_count
from ._geometric import geometric_sum as geometric_sum
from ._geometric import safe_power as safe_power
