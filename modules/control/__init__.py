"""Vehicle control: path interface, Stanley or PD steering, PI speed, fail-safe braking."""

from modules.control.module import Control as MODULE

__all__ = ["MODULE"]
