"""`printable`: text from the wire or a file, safe on a terminal and bounded."""

from topseg.core.printable import CUT_MARK, MAX_SHOWN, printable


def test_plain_text_is_shown_as_it_is():
    assert printable("default.npz") == "default.npz"
    assert printable("Köln 3.5 m") == "Köln 3.5 m"
    assert printable(42) == "42"


def test_control_characters_and_escape_codes_are_shown_escaped():
    assert printable("a\x1b[31mred\r\n\tx\x00\x07") == "a\\x1b[31mred\\r\\n\\tx\\x00\\x07"
    assert printable("left\u202eright\u200b") == "left\\u202eright\\u200b"  # bidi, zero width
    assert printable("\U000e0001") == "\\U000e0001"
    assert printable("a\\x1b") == "a\\\\x1b"  # a backslash is escaped: no look-alike


def test_the_result_is_bounded_and_an_escape_is_never_cut_in_two():
    assert printable("x" * MAX_SHOWN) == "x" * MAX_SHOWN
    long = printable("x" * 10**6)
    assert len(long) == MAX_SHOWN and long.endswith(CUT_MARK)
    for n in range(1, 40):
        shown = printable("\x1b" * n, 20)
        assert len(shown) <= 20
        body = shown.removesuffix(CUT_MARK)
        assert body == "\\x1b" * (len(body) // 4)
    assert printable("abcdef", 2) == "a" + CUT_MARK  # room for one character at least
