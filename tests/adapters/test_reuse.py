"""``adapters.call.reuse_for``: what a sampling loop keeps between calls (lengths, forced frames,
plans), against computing every time."""
import threading

import torch

import smdm_plugin.adapters.call as call


def _counting():
    made = []

    def compute(value):
        def make():
            made.append(value)
            return torch.tensor(value)
        return make
    return made, compute


def test_a_result_is_kept_for_the_same_unchanged_tensors_and_key_only():
    call._REUSED.clear()
    made, compute = _counting()
    a, b = torch.zeros(3), torch.ones(2)
    first = call.reuse_for((a, None, b), ("k", 1), compute(1))
    assert call.reuse_for((a, None, b), ("k", 1), compute(2)) is first and made == [1]
    call.reuse_for((a, None, b.clone()), ("k", 1), compute(3))          # another tensor of equal values
    call.reuse_for((a, b, None), ("k", 1), compute(4))                  # another position of the None
    call.reuse_for((a, None, b), ("k", 2), compute(5))                  # another key
    call.reuse_for(a, ("k", 1), compute(6))                             # one tensor is not the tuple of three
    assert made == [1, 3, 4, 5, 6]
    b.add_(1)                                                           # an in-place change: a new version
    assert int(call.reuse_for((a, None, b), ("k", 1), compute(7))) == 7 and made[-1] == 7
    assert call.reuse_for((a, None, b), ("k", 1), compute(8)) is not first and made[-1] == 7


def test_inference_tensors_keep_nothing():
    call._REUSED.clear()
    made, compute = _counting()
    with torch.inference_mode():
        t = torch.zeros(3)
        call.reuse_for(t, ("k",), compute(1))
        t.add_(1)                                                       # no version counter to see this
        call.reuse_for(t, ("k",), compute(2))
    assert made == [1, 2] and not call._REUSED


def test_the_most_recently_used_results_are_kept():
    call._REUSED.clear()
    made, compute = _counting()
    ts = [torch.zeros(1) for _ in range(call.REUSE_KEEP + 1)]
    for i, t in enumerate(ts):
        call.reuse_for(t, ("k",), compute(i))
        call.reuse_for(ts[0], ("k",), compute(-1))                     # used at every step: stays
    assert made == list(range(len(ts))) and len(call._REUSED) == call.REUSE_KEEP
    call.reuse_for(ts[1], ("k",), compute(100))                        # the least recently used: gone
    assert made[-1] == 100


def test_threads_reusing_at_once_get_their_own_results():
    call._REUSED.clear()
    ts = [torch.full((1,), float(i)) for i in range(32)]
    bad = []

    def run(offset):
        for r in range(200):
            t = ts[(r + offset) % len(ts)]
            got = call.reuse_for(t, ("k",), lambda: t.clone())
            if not torch.equal(got, t):
                bad.append((offset, r))
    threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not bad
