"""Shared steps of the apps' tests."""

import pytest

from apps import redirect


def interrupt_redirect_before_assembly(args: list[str], monkeypatch) -> None:
    """Run ``apps.redirect`` on ``args`` and kill it after its chunks, before the final file is assembled."""
    def crash(*a, **k):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(redirect, "assemble", crash)
        with pytest.raises(KeyboardInterrupt):
            redirect.main(args)
