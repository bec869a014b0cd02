"""Memory cells: one interface, `init_carry()` and `__call__(carry, xs, starts)`."""

from ._base import AbstractMemory as AbstractMemory
from ._base import stop_gradient_carry as stop_gradient_carry
from ._gru import GRU as GRU
from ._layers import MLP as MLP
from ._layers import Dense as Dense
from ._layers import orthogonal as orthogonal
from ._memoryless import Memoryless as Memoryless
from ._trxl import TransformerXL as TransformerXL
from ._trxl import TrXLCarry as TrXLCarry
