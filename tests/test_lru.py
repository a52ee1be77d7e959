import threading

from skyview.core.lru import LRU


def test_the_least_recently_used_goes_first_and_a_read_counts_as_use():
    c = LRU(2)
    c.put("a", 1)
    c.put("b", 2)
    assert c.get("a") == 1  # a is now the newest
    c.put("c", 3)
    assert "b" not in c and c.get("a") == 1 and c.get("c") == 3 and len(c) == 2
    made = []
    assert c.get_or_make("a", lambda: made.append(1)) == 1 and not made  # kept: not made again
    assert c.get_or_make("d", lambda: 4) == 4 and "c" not in c
    assert c.pop("d") == 4 and c.get("d", "none") == "none"


def test_threads_using_one_cache_keep_it_bounded_and_whole():
    c = LRU(4)
    errors = []

    def work(k):
        try:
            for i in range(2000):
                key = (k * 7 + i) % 11
                assert c.get_or_make(key, lambda: key * 10) == key * 10
        except Exception as exc:  # (an assertion or a KeyError from a broken eviction)
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(c) <= 4
