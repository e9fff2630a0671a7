"""Is the board's flash filesystem FAT? Then an update must not run: renaming files over old ones is power-cut
safe on littlefs (the ESP8266's filesystem since MicroPython 1.13) but not on FAT (a board upgraded from an
older MicroPython without an erase keeps FAT: a cut mid-swap can leave the directory unreadable).

Loaded by the updater before it fetches anything; `wsnav firmware deploy` (firmware/deploy.py) runs this file's
text at the board's REPL before it copies anything. Reads the filesystem's first block through the ESP8266
port's `flashbdev` (what its _boot.py mounts): a FAT boot sector ends in 55 AA and names "FAT" at byte 54
(FAT12/16) or 82 (FAT32); littlefs writes "littlefs" at byte 8.
"""


def fat() -> bool:
    """True if the flash holds a FAT filesystem; False for littlefs, or where there is no flash block device."""
    try:
        from flashbdev import bdev
    except ImportError:
        return False
    if bdev is None:  # flashbdev found no room for a filesystem
        return False
    buf = bytearray(512)
    bdev.readblocks(0, buf)
    return buf[510] == 0x55 and buf[511] == 0xAA and (buf[54:57] == b"FAT" or buf[82:85] == b"FAT")
