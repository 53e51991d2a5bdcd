"""`jaxmap bench`: n3, imt and slam suites (one module each) and what they share."""


def base_overrides(args, data: str, output: str | None = None) -> list[str]:
    """Config overrides every bench starts from: the scene directory, the output directory (if
    given), the user's `--set`s, and `--frames` as data.end_frame."""
    base = [f"data.path={data}"] + ([f"output={output}"] if output else []) + list(args.overrides)
    if args.frames:
        base.append(f"data.end_frame={args.frames}")
    return base
