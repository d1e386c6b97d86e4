"""The avrdude command that flashes the trigger firmware through an Arduino bootloader."""

from __future__ import annotations

from pathlib import Path

# Bootloader settings of the boards: (avrdude part, programmer, baud). The Nano's old bootloader
# listens at 57600, optiboot (Uno, new Nano) at 115200; the Leonardo/Micro's Caterina speaks avr109
# and is entered by opening the port at 1200 baud first.
BOARDS: dict[str, tuple[str, str, int, str]] = {
    "uno": ("atmega328p", "arduino", 115200, "atmega328p"),
    "nano": ("atmega328p", "arduino", 115200, "atmega328p"),
    "nano-old": ("atmega328p", "arduino", 57600, "atmega328p"),
    "leonardo": ("atmega32u4", "avr109", 57600, "atmega32u4"),
    "micro": ("atmega32u4", "avr109", 57600, "atmega32u4"),
}


def avrdude_command(board: str, port: str, hex_path: str | Path) -> list[str]:
    if board not in BOARDS:
        raise ValueError(f"unknown board {board!r}: one of {', '.join(BOARDS)}")
    part, programmer, baud, _ = BOARDS[board]
    return ["avrdude", "-p", part, "-c", programmer, "-P", port, "-b", str(baud), "-D",
            "-U", f"flash:w:{hex_path}:i"]


def firmware_mcu(board: str) -> str:
    if board not in BOARDS:
        raise ValueError(f"unknown board {board!r}: one of {', '.join(BOARDS)}")
    return BOARDS[board][3]
