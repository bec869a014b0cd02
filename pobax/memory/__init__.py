"""Memory cells: one interface, `init_carry()` and `__call__(carry, xs, starts)` (the contract: pobax/memory/_base.py;
a test of it for any cell: `pobax.memory.testing`). Built-in memories by name: `MEMORIES`; a user's cell: `package.module:ClassName`
(`memory_class`)."""

from ._base import AbstractMemory as AbstractMemory
from ._base import check_inputs as check_inputs
from ._ffm import FFM as FFM
from ._gru import GRU as GRU
from ._layers import MLP as MLP
from ._layers import Dense as Dense
from ._layers import flat_draw as flat_draw
from ._layers import orthogonal as orthogonal
from ._layers import with_matmul_batch as with_matmul_batch
from ._lstm import LSTM as LSTM
from ._lstm import LSTMCarry as LSTMCarry
from ._lru import LRU as LRU
from ._memax import S6 as S6
from ._memoryless import Memoryless as Memoryless
from ._trxl import TransformerXL as TransformerXL
from ._trxl import TrXLCarry as TrXLCarry
from ._registry import MEMORIES as MEMORIES
from ._registry import PAPER_MEMORIES as PAPER_MEMORIES
from ._registry import ZOO as ZOO
from ._registry import memory_class as memory_class
