"""nodes._common.background_thread lowers the priority of the calling thread only (Linux keeps a
nice value per thread): the node's stream thread keeps its own."""
import os
import sys
import threading

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice is Linux's")


def test_only_the_calling_thread_is_niced():
    from maglev_ros.nodes._common import BACKGROUND_NICE, background_thread
    main_before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen = {}

    def work():
        tid = threading.get_native_id()
        seen["before"] = os.getpriority(os.PRIO_PROCESS, tid)
        background_thread()
        seen["after"] = os.getpriority(os.PRIO_PROCESS, tid)

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen["after"] == min(19, seen["before"] + BACKGROUND_NICE)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main_before
