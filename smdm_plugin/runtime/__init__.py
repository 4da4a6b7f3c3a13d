"""How a model runs, whatever its family: graph capture (``compile``), distributed training
(``distributed``), kernel launches counted (``launches``)."""
