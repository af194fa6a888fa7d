# Type stub for the optional C module built from _speedups.c (see bridge/speedups.py).
def bind_attitude_frame(
    slots_cls: type, frame_cls: type, flags_table: tuple[object, ...], seq_max: int, /
) -> None: ...
def decode_attitude_lines(data: bytes, /) -> list[object] | None: ...
def solve(
    consts: tuple[object, ...],
    mx: float,
    my: float,
    mz: float,
    ax: float,
    ay: float,
    az: float,
    /,
) -> (
    tuple[
        float,
        float,
        float,
        float,
        float | None,
        float | None,
        str,
        tuple[float, float, float, float],
        tuple[float, float, float],
        tuple[float, float, float],
        float,
        float,
        bool,
        float,
    ]
    | None
): ...
