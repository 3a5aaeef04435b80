"""The RAPID-subset interpreter runs small RAPID programs with the semantics of the IRC5 (see docs/rapid_subset.md)."""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

import pytest

from maniskill_irb120.abb.emulator.rapid import (
    ERROR_CODES,
    Builtins,
    Interpreter,
    ManualClock,
    RapidError,
    RapidRuntimeError,
    RapidStopped,
    RapidSyntaxError,
    Record,
    Ref,
    make_value,
)


def module(body: str, data: str = "", routines: str = "") -> str:
    return f"MODULE TestMod\n{data}\nPROC main()\n{body}\nENDPROC\n{routines}\nENDMODULE\n"


def run(body: str, data: str = "", routines: str = "", **kwargs) -> Interpreter:
    interp = Interpreter(module(body, data, routines), **kwargs)
    assert interp.run() == "completed"
    return interp


def expr(text: str, type_name: str = "num"):
    """The value of one RAPID expression."""
    return run(f"r := {text};", data=f"VAR {type_name} r;").get("r")


# ---- expressions ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, value",
    [
        ("1 + 2 * 3", 7.0),
        ("(1 + 2) * 3", 9.0),
        ("-2 * 3 + 10", 4.0),
        ("10 - 4 - 3", 3.0),
        ("8 / 2 / 2", 2.0),
        ("7 DIV 2", 3.0),
        ("-7 DIV 2", -3.0),
        ("7 MOD 3", 1.0),
        ("-7 MOD 3", -1.0),
        ("2 + 7 DIV 2 * 2", 8.0),
        ("9E9", 9e9),
        ("1.5e-3 * 2", 0.003),
        ("0xFF + 1", 256.0),
        ("- - 3", 3.0),
    ],
)
def test_arithmetic_and_precedence(text, value):
    assert expr(text) == pytest.approx(value)


@pytest.mark.parametrize(
    "text, value",
    [
        ("NOT 1 = 2", True),  # NOT binds looser than comparisons
        ("TRUE OR FALSE AND FALSE", True),  # AND binds tighter than OR
        ("(TRUE OR FALSE) AND FALSE", False),
        ("TRUE XOR TRUE", False),
        ("1 + 1 = 2 AND 3 > 2 AND 2 <= 2 AND 1 <> 2 AND (2 >= 3) = FALSE", True),
        ("NOT TRUE AND FALSE", False),
        ('"ab" = "a" + "b"', True),
    ],
)
def test_boolean_operators_and_comparisons(text, value):
    assert expr(text, "bool") is value


def test_strings_concatenate_and_unescape():
    assert expr(r'"say ""hi"" " + "C:\\dir" + "\0D\0A"', "string") == 'say "hi" C:\\dir\r\n'


def test_pos_arithmetic():
    got = run(
        "c := a + b; d := a - b; e := 2 * a; f := a * 0.5;",
        data="VAR pos a := [1, 2, 3]; VAR pos b := [10, 20, 30]; VAR pos c; VAR pos d; VAR pos e; VAR pos f;",
    )
    assert got.get("c").to_list() == [11, 22, 33]
    assert got.get("d").to_list() == [-9, -18, -27]
    assert got.get("e").to_list() == [2, 4, 6]
    assert got.get("f").to_list() == [0.5, 1, 1.5]


def test_division_by_zero_is_a_rapid_error_with_the_line():
    with pytest.raises(RapidRuntimeError) as e:
        run("x := 1;\nx := x / 0;", data="VAR num x;")
    assert e.value.errno == ERROR_CODES["ERR_DIVZERO"] and e.value.line == 5 and e.value.routine == "main"


# ---- data -------------------------------------------------------------------------------------------
ROBTARGET = "[[100, 200, 300], [0, 0, 1, 0], [0, -1, 0, 1], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]]"


def test_records_aggregates_fields_and_value_copies():
    interp = run(
        "p2 := p1;\n p2.trans.x := 5;\n p2.rot := [1, 0, 0, 0];\n x := p1.trans.z + p2.trans.x;\n"
        "same := p1.trans = [100, 200, 300] AND p2 <> p1;",
        data=f"VAR robtarget p1 := {ROBTARGET};\nVAR robtarget p2;\nVAR num x;\nVAR bool same;",
    )
    p1, p2 = interp.get("p1"), interp.get("p2")
    assert isinstance(p1, Record) and p1.type == "robtarget"
    assert p1.trans.x == 100 and p1["trans"]["y"] == 200 and p1.robconf.cf4 == -1
    assert p1.extax.eax_a == pytest.approx(9e9, rel=1e-7)  # a num: float32(9E9)
    assert p2.trans.x == 5 and p2.rot.to_list() == [1, 0, 0, 0]  # the copy changed, the original did not
    assert p1.rot.to_list() == [0, 0, 1, 0]
    assert interp.get("x") == 305 and interp.get("same") is True
    assert p1.to_python()["trans"] == {"x": 100, "y": 200, "z": 300}


def test_record_defaults_and_aggregate_size_check():
    interp = run("", data="VAR robtarget p; VAR jointtarget j;")
    assert interp.get("p").rot.to_list() == [1, 0, 0, 0] and interp.get("j").extax.eax_f == 9e9
    with pytest.raises(RapidRuntimeError, match="4 components"):
        run("p := [1, 2, 3];", data="VAR orient p;")


def test_user_records():
    src = """MODULE M
    RECORD cmdframe
      num id;
      pos target;
      string tag;
    ENDRECORD
    VAR cmdframe frames{2};
    PROC main()
      frames{2} := [7, [1, 2, 3], "go"];
      frames{1}.target.z := frames{2}.target.y * 10;
    ENDPROC
    ENDMODULE"""
    interp = Interpreter(src)
    interp.run()
    assert [f.to_python() for f in interp.get("frames")] == [
        {"id": 0, "target": {"x": 0, "y": 0, "z": 20}, "tag": ""},
        {"id": 7, "target": {"x": 1, "y": 2, "z": 3}, "tag": "go"},
    ]
    with pytest.raises(RapidRuntimeError, match="predefined"):
        Interpreter("MODULE M RECORD pos num a; ENDRECORD ENDMODULE")


def test_arrays_are_one_based_and_bounds_checked():
    interp = run(
        "FOR i FROM 1 TO 3 DO a{i} := i * i; ENDFOR\n m{2, 3} := 7;\n n := Dim(a, 1) + Dim(m, 2) + a{3};",
        data="VAR num a{3}; VAR num m{2, 3}; VAR num n;",
    )
    assert interp.get("a") == [1, 4, 9] and interp.get("m") == [[0, 0, 0], [0, 0, 7]] and interp.get("n") == 15
    with pytest.raises(RapidRuntimeError) as e:
        run("a{4} := 1;", data="VAR num a{3};")
    assert e.value.errno == ERROR_CODES["ERR_OUTOFBND"]


def test_standard_data():
    interp = run("", data="VAR speeddata s; VAR zonedata z; VAR tooldata t;")
    for name, value in [("s", "v100"), ("z", "z10"), ("t", "tool0")]:
        interp.set(name, interp.get(value))
    assert interp.get("s").to_list() == [100, 500, 5000, 1000]
    assert interp.get("fine").finep is True and interp.get("z").pzone_tcp == 10 and interp.get("z").zone_ori == 1.5
    assert interp.get("t").tload.mass == pytest.approx(0.001, rel=1e-7)  # a num: float32(0.001)
    assert interp.get("wobj0").ufprog is True


def test_get_set_and_const():
    interp = run("n := n + 1;", data="VAR num n := 1; CONST num k := 2;")
    interp.set("n", 41)
    assert interp.run() == "completed" and interp.get("N") == 42
    with pytest.raises(RapidRuntimeError, match="CONST"):
        interp.set("k", 3)
    with pytest.raises(RapidRuntimeError, match="CONST"):
        run("k := 3;", data="CONST num k := 2;")


# ---- control flow -----------------------------------------------------------------------------------
@pytest.mark.parametrize("x, branch", [(1, "one"), (2, "two"), (5, "many")])
def test_if_elseif_else(x, branch):
    body = f"""x := {x};
    IF x = 1 THEN s := "one";
    ELSEIF x = 2 THEN s := "two";
    ELSE s := "many";
    ENDIF
    IF x > 4 s := s + "!";"""
    assert run(body, data="VAR num x; VAR string s;").get("s") == branch + ("!" if x > 4 else "")


def test_while_and_for_with_steps():
    interp = run(
        """WHILE n < 5 DO Incr n; ENDWHILE
        FOR i FROM 1 TO 10 STEP 3 DO up := up + ValToStr(i) + ","; ENDFOR
        FOR i FROM 10 TO 1 STEP -4 DO down := down + ValToStr(i) + ","; ENDFOR
        FOR j FROM 3 TO 1 DO implicit := implicit + ValToStr(j); ENDFOR""",
        data="VAR num n; VAR string up; VAR string down; VAR string implicit;",
    )
    assert interp.get("n") == 5
    assert interp.get("up") == "1,4,7,10," and interp.get("down") == "10,6,2," and interp.get("implicit") == "321"
    with pytest.raises(RapidRuntimeError, match="undefined name i"):
        run("FOR i FROM 1 TO 2 DO ENDFOR\n x := i;", data="VAR num x;")


@pytest.mark.parametrize("x, out", [(1, "a"), (3, "bc"), (4, "bc"), (9, "d")])
def test_test_case_default(x, out):
    body = f"""TEST {x}
    CASE 1: s := "a";
    CASE 3, 4: s := "bc";
    DEFAULT: s := "d";
    ENDTEST"""
    assert run(body, data="VAR string s;").get("s") == out


def test_func_return_and_recursion():
    routines = """FUNC num Fact(num n)
      IF n <= 1 RETURN 1;
      RETURN n * Fact(n - 1);
    ENDFUNC"""
    assert run("x := Fact(5);", data="VAR num x;", routines=routines).get("x") == 120
    with pytest.raises(RapidRuntimeError, match="without RETURN"):
        run("x := F();", data="VAR num x;", routines="FUNC num F() ENDFUNC")


def test_optional_args_present_switches_and_alternatives():
    routines = r"""PROC Log(string msg, \num level, \switch loud | switch quiet)
      s := s + msg;
      IF Present(level) s := s + ":" + ValToStr(level);
      IF Present(loud) s := s + "!";
      IF Present(quiet) s := s + ".";
      s := s + ";";
      Forward msg \level?level;
    ENDPROC
    PROC Forward(string msg, \num level)
      IF Present(level) t := t + ValToStr(level);
    ENDPROC"""
    body = r"""Log "a"; Log "b" \level:=2; Log "c" \Loud; Log "d", \level:=3 \quiet;"""
    interp = run(body, data="VAR string s; VAR string t;", routines=routines)
    assert interp.get("s") == "a;b:2;c!;d:3.;" and interp.get("t") == "23"
    with pytest.raises(RapidRuntimeError, match="exclude each other"):
        run(r'Log "x" \loud \quiet;', data="VAR string s; VAR string t;", routines=routines)
    with pytest.raises(RapidRuntimeError) as e:
        run(r"P;", routines=r"PROC P(\num x) x := x + 1; ENDPROC")
    assert e.value.errno == ERROR_CODES["ERR_NOTPRES"]


def test_inout_var_and_in_parameters():
    routines = """PROC Bump(INOUT num x, VAR pos p, num copy)
      x := x + 1; p.z := 99; copy := 0;
    ENDPROC"""
    interp = run("Bump a{2}, rt.trans, n; Bump n, rt.trans, n;", data="VAR num a{2}; VAR robtarget rt; VAR num n := 7;",
                 routines=routines)  # fmt: skip
    assert interp.get("a") == [0, 1] and interp.get("n") == 8 and interp.get("rt").trans.z == 99
    with pytest.raises(RapidRuntimeError, match="must be a variable"):
        run("Bump 1 + 1, rt.trans, 0;", data="VAR robtarget rt;", routines=routines)


def test_case_insensitive_keywords_identifiers_and_builtins_comments_and_header():
    src = """%%%
      VERSION:1
      LANGUAGE:ENGLISH
    %%%
    module CaseMod(SYSMODULE)  ! a comment
      var NUM Count := 1;  ! another
      proc MAIN()
        while count < 3 do incr COUNT; endwhile
        if COUNT = 3 then tpwrite "n=" \\num:=Count; endif
      endproc
    endmodule"""
    interp = Interpreter(src)
    assert interp.run("Main") == "completed" and interp.get("count") == 3 and interp.tp_log == ["n=3"]


def test_exit_and_stop():
    assert Interpreter(module("EXIT;\n n := 1;", "VAR num n;")).run() == "exit"
    interp = Interpreter(module("Stop;\n n := 1;", "VAR num n;"))
    assert interp.run() == "stop" and interp.get("n") == 0


# ---- error handling ---------------------------------------------------------------------------------
def flaky(failures: int, errno: str = "ERR_DEV_MAXTIME"):
    """A builtin that raises ``errno`` its first ``failures`` calls, then returns the call count."""
    calls = []

    def fn() -> float:
        calls.append(1)
        if len(calls) <= failures:
            raise RapidError(errno, "simulated")
        return len(calls)

    return fn, calls


def test_retry_reexecutes_the_failing_statement():
    fn, calls = flaky(2)
    body = """n := Flaky();
    s := "after";
    ERROR
      IF ERRNO = ERR_DEV_MAXTIME THEN
        Incr retries;
        RETRY;
      ENDIF"""
    interp = run(body, data="VAR num n; VAR num retries; VAR string s;", builtins={"Flaky": fn})
    assert interp.get("n") == 3 and interp.get("retries") == 2 and interp.get("s") == "after"
    assert interp.errno == ERROR_CODES["ERR_DEV_MAXTIME"]


def test_retry_limit_then_the_error_goes_to_the_caller():
    fn, calls = flaky(100, "ERR_SOCK_TIMEOUT")
    routines = """PROC Inner()
      n := Flaky();
    ERROR
      RETRY;
    ENDPROC"""
    body = """Inner;
    ERROR
      IF ERRNO = ERR_SOCK_TIMEOUT s := "caller caught";
      TRYNEXT;"""
    interp = run(body, data="VAR num n; VAR string s;", routines=routines, builtins={"Flaky": fn}, max_retries=3)
    assert len(calls) == 4 and interp.get("s") == "caller caught"
    calls.clear()
    with pytest.raises(RapidRuntimeError) as e:
        run("Inner;", data="VAR num n;", routines=routines, builtins={"Flaky": fn}, max_retries=2)
    assert len(calls) == 3 and e.value.errno == ERROR_CODES["ERR_SOCK_TIMEOUT"] and e.value.routine == "Inner"


def test_trynext_continues_after_the_failing_statement():
    body = """WHILE i < 3 DO
      Incr i;
      x := 10 / (i - 2);
      s := s + ValToStr(x) + ",";
    ENDWHILE
    ERROR
      s := s + "div0,";
      TRYNEXT;"""
    # TRYNEXT resumes at the statement after the failing one: the old x is appended again
    assert run(body, data="VAR num i; VAR num x; VAR string s;").get("s") == "-10,div0,-10,10,"


def test_raise_goes_to_the_callers_handler():
    routines = """PROC Check(num v)
      IF v > 10 RAISE ERR_ARGVALERR;
      s := s + "ok,";
    ERROR
      s := s + "inner,";
      RAISE;
    ENDPROC
    PROC Convert()
      Check 20;
    ERROR
      RAISE ERR_ROBLIMIT;
    ENDPROC"""
    body = """Check 1;
    Check 11;
    Convert;
    ERROR
      s := s + ValToStr(ERRNO = ERR_ARGVALERR) + ValToStr(ERRNO = ERR_ROBLIMIT) + ",";
      TRYNEXT;"""
    assert run(body, data="VAR string s;", routines=routines).get("s") == "ok,inner,TRUEFALSE,inner,FALSETRUE,"


def test_return_from_the_handler_and_implicit_raise_at_its_end():
    routines = """FUNC bool Reachable(num x)
      y := 1 / x;
      RETURN TRUE;
    ERROR
      RETURN FALSE;
    ENDFUNC
    PROC FallsOff()
      y := 1 / 0;
    ERROR
      s := "handled once";
    ENDPROC"""
    interp = run("a := Reachable(2); b := Reachable(0);", data="VAR bool a; VAR bool b; VAR num y; VAR string s;",
                 routines=routines)  # fmt: skip
    assert interp.get("a") is True and interp.get("b") is False
    with pytest.raises(RapidRuntimeError) as e:
        interp.call("FallsOff")
    assert e.value.errno == ERROR_CODES["ERR_DIVZERO"] and interp.get("s") == "handled once"


def test_book_errno_user_errors_and_errors_inside_a_handler():
    routines = """PROC Boom()
      RAISE ERR_MINE;
    ERROR
      IF ERRNO = ERR_MINE x := 1 / 0;
    ENDPROC"""
    data = "VAR errnum ERR_MINE := -1; VAR num x; VAR num seen;"
    body = "BookErrNo ERR_MINE;\n Boom;\nERROR\n seen := ERRNO;\n TRYNEXT;"
    interp = run(body, data=data, routines=routines)
    assert interp.get("ERR_MINE") >= 1000 and interp.get("seen") == ERROR_CODES["ERR_DIVZERO"]


def test_unhandled_error_reports_errno_routine_and_line():
    src = """MODULE M
    PROC main()
      Deep;
    ENDPROC
    PROC Deep()
      VAR num x;
      x := 1;
      x := Sqrt(-x);
    ENDPROC
    ENDMODULE"""
    with pytest.raises(RapidRuntimeError) as e:
        Interpreter(src).run()
    assert (e.value.errno, e.value.routine, e.value.line) == (ERROR_CODES["ERR_ARGVALERR"], "Deep", 8)
    assert "line 8" in str(e.value) and "ERR_ARGVALERR" in str(e.value)


def test_syntax_error_names_line_column_and_expectation():
    with pytest.raises(RapidSyntaxError) as e:
        Interpreter("MODULE M\nPROC main()\n  x := 1\n  y := 2;\nENDPROC\nENDMODULE")
    assert e.value.line == 4 and e.value.column == 3 and "line 4" in str(e.value) and '";"' in str(e.value)
    with pytest.raises(RapidSyntaxError, match="line 4"):
        Interpreter("MODULE M\nPROC main()\n  IF x THEN\nENDPROC\nENDMODULE")


@pytest.mark.parametrize(
    "body, data, message",
    [
        ("x := y;", "VAR num x;", "undefined name y"),
        ('x := "a";', "VAR num x;", "cannot assign a string to a num"),
        ("x := 1 + TRUE;", "VAR num x;", "not defined for num and bool"),
        ("Nope 1;", "", "unknown procedure Nope"),
        ("P 1, 2;", "", "takes 1 argument"),
        ("IF 1 THEN ENDIF", "", "needs a bool"),
    ],
)
def test_program_faults_are_reported_with_lines(body, data, message):
    with pytest.raises(RapidRuntimeError, match=message) as e:
        run(body, data=data, routines="PROC P(num a) ENDPROC")
    assert e.value.line == 4 and e.value.errno is None


# ---- rawbytes -----------------------------------------------------------------------------------------
INTX = [("USINT", "B", 200), ("UINT", "H", 65000), ("UDINT", "I", 4000000000), ("SINT", "b", -100)]
INTX += [("INT", "h", -30000), ("DINT", "i", -2000000000)]


@pytest.mark.parametrize("network", [False, True])
@pytest.mark.parametrize("intx, fmt, value", INTX)
def test_pack_unpack_intx_matches_struct(intx, fmt, value, network):
    net = r" \Network" if network else ""
    interp = run(
        f"PackRawBytes {value}, raw, 3{net} \\IntX:={intx};\n UnpackRawBytes raw, 3, back{net} \\IntX:={intx};",
        data="VAR rawbytes raw; VAR num back;",
    )
    raw = interp.get("raw")
    assert bytes(raw) == b"\0\0" + struct.pack((">" if network else "<") + fmt, value)
    assert interp.get("back") == value


def test_pack_unpack_float4_ascii_hex1_copy_clear():
    interp = run(
        r"""PackRawBytes 3.25, raw, 1 \Float4;
        PackRawBytes "OK", raw, RawBytesLen(raw) + 1 \ASCII;
        PackRawBytes 255, raw, RawBytesLen(raw) + 1 \Hex1;
        UnpackRawBytes raw, 1, f \Float4;
        UnpackRawBytes raw, 5, s \ASCII:=2;
        UnpackRawBytes raw, 7, h \Hex1;
        CopyRawBytes raw, 5, other, 1 \NoOfBytes:=2;
        n := RawBytesLen(raw);
        ClearRawBytes raw \FromIndex:=5;""",
        data="VAR rawbytes raw; VAR rawbytes other; VAR num f; VAR string s; VAR num h; VAR num n;",
    )
    assert interp.get("n") == 7 and bytes(interp.get("raw")) == struct.pack("<f", 3.25)
    assert interp.get("f") == 3.25 and interp.get("s") == "OK" and interp.get("h") == 255
    assert bytes(interp.get("other")) == b"OK"


def test_unpack_past_the_valid_length_and_bad_values_are_rapid_errors():
    with pytest.raises(RapidRuntimeError) as e:
        run(r"UnpackRawBytes raw, 1, x \IntX:=UINT;", data="VAR rawbytes raw; VAR num x;")
    assert e.value.errno == ERROR_CODES["ERR_OUTOFBND"]
    with pytest.raises(RapidRuntimeError) as e:
        run(r"PackRawBytes 300, raw, 1 \IntX:=USINT;", data="VAR rawbytes raw;")
    assert e.value.errno == ERROR_CODES["ERR_ARGVALERR"]


# ---- language built-ins -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, value",
    [
        ("Sin(30)", 0.5),
        ("Cos(60)", 0.5),
        ("ATan2(1, 1)", 45.0),
        ("ACos(0)", 90.0),
        ("Sqrt(16) + Abs(-2)", 6.0),
        ("Pow(2, 10)", 1024.0),
        (r"Round(0.3852 \Dec:=2)", 0.39),
        ("Round(2.5)", 3.0),
        ("Round(-2.5)", -3.0),
        (r"Trunc(2.789 \Dec:=1)", 2.7),
        ('StrLen("hello")', 5.0),
        ("BitAnd(12, 10) + BitOr(12, 10) + BitXOr(12, 10)", 8 + 14 + 6),
        ("BitNeg(1) + BitLSh(129, 1) + BitRSh(16, 2)", 254 + 2 + 4),
        (r'StrToByte("7B" \Hex)', 123.0),
    ],
)
def test_math_string_and_bit_functions(text, value):
    assert expr(text) == pytest.approx(value)


@pytest.mark.parametrize(
    "text, value",
    [
        ('StrPart("robot", 2, 3)', "obo"),
        ("NumToStr(3.14159, 2)", "3.14"),
        ("NumToStr(2, 1)", "2.0"),
        ("ValToStr(1/3)", "0.333333"),
        ("ValToStr([1, 2.5, TRUE])", "[1,2.5,TRUE]"),
        (r"ByteToStr(10 \Hex) + ByteToStr(65 \Char)", "0AA"),
    ],
)
def test_string_functions(text, value):
    assert expr(text, "string") == value


def test_waittime_and_clock_use_the_injected_clock():
    clock = ManualClock()
    interp = run(
        "ClkReset c; ClkStart c; WaitTime 1.5; WaitTime 0.25; ClkStop c; WaitTime 5; t := ClkRead(c);",
        data="VAR clock c; VAR num t;",
        clock=clock,
    )
    assert clock.sleeps == [1.5, 0.25, 5] and interp.get("t") == 1.75


# ---- execution control ----------------------------------------------------------------------------------
def test_request_stop_ends_a_server_loop_from_another_thread():
    interp = Interpreter(module("WHILE TRUE DO\n Incr n;\n WaitTime 0.001;\n ENDWHILE", "VAR num n;"))
    outcome = []

    def target():
        try:
            interp.run()
        except RapidStopped as e:
            outcome.append(e)

    thread = threading.Thread(target=target)
    thread.start()
    deadline = time.monotonic() + 5
    while interp.get("n") < 3 and time.monotonic() < deadline:
        time.sleep(0.005)
    interp.request_stop()
    thread.join(timeout=5)
    assert not thread.is_alive() and len(outcome) == 1 and interp.get("n") >= 3


def test_statement_budget():
    with pytest.raises(RapidStopped, match="budget"):
        run("WHILE TRUE DO Incr n; ENDWHILE", data="VAR num n;", max_statements=100)


def test_call_from_python_with_by_reference_arguments():
    routines = """FUNC num Scale(num v, \\num k)
      IF Present(k) RETURN v * k;
      RETURN v;
    ENDFUNC
    PROC Swap(INOUT num a, INOUT num b)
      VAR num t;
      t := a; a := b; b := t;
    ENDPROC"""
    interp = Interpreter(module("", "VAR num x := 1; VAR num y := 2;", routines))
    assert interp.call("Scale", 3) == 3 and interp.call("scale", 3, k=4) == 12
    interp.call("Swap", interp.ref("x"), interp.ref("y"))
    assert (interp.get("x"), interp.get("y")) == (2, 1)
    assert interp.call("StrLen", "abc") == 3


# ---- builtins registered by an emulator -------------------------------------------------------------------
def test_registered_builtins_get_positional_optional_switch_and_ref_args():
    reg = Builtins()
    seen = {}

    @reg.register("ReadBlock", refs=[1, "Count"])
    def read_block(dev, raw: Ref, *, Time=None, Bin=False, Count=None):  # noqa: N803 - RAPID option names
        seen.update(dev=dev.type, time=Time, bin=Bin)
        if Time is not None and Time < 1:
            raise RapidError("ERR_DEV_MAXTIME", "no data")
        raw.value.write(1, b"\x01\x02")
        Count.value = 2

    @reg.register(with_interp=True)
    def Scaled(interp, v, factor=2.0):  # noqa: N802 - a RAPID name
        return v * factor + interp.get("offset")

    body = r"""ReadBlock dev, raw \Time:=0.5 \Bin \Count:=n;
    s := s + "got " + ValToStr(n) + ",";
    x := Scaled(3) + Scaled(1 \factor:=10);
    ERROR
      IF ERRNO = ERR_DEV_MAXTIME THEN
        s := "timeout,";
        ReadBlock dev, raw \Time:=2 \Count:=n;
        TRYNEXT;
      ENDIF"""
    data = "VAR iodev dev; VAR rawbytes raw; VAR num n; VAR string s; VAR num x; VAR num offset := 100;"
    interp = run(body, data=data, builtins=reg)
    assert interp.get("s") == "timeout,got 2," and bytes(interp.get("raw")) == b"\x01\x02"
    assert seen == {"dev": "iodev", "time": 2.0, "bin": False} and interp.get("x") == 106 + 110


def test_builtins_override_and_python_exceptions_are_fatal():
    def boom():
        raise KeyError("bad")

    with pytest.raises(RapidRuntimeError, match="Boom failed: KeyError") as e:
        run("Boom;", builtins={"Boom": boom})
    assert e.value.line == 4 and isinstance(e.value.__cause__, KeyError)
    assert run('x := StrLen("a");', data="VAR num x;", builtins={"StrLen": lambda s: 42}).get("x") == 42
    with pytest.raises(RapidRuntimeError, match=r"no optional argument \\Foo"):
        run(r"TPWrite 1 \Foo:=2;")


def test_ref_gives_python_access_to_a_component():
    interp = run("", data=f"VAR robtarget p := {ROBTARGET};")
    ref = Ref(interp.ref("p").cell, ("trans", "x"))
    ref.value = 7
    assert interp.get("p").trans.x == 7.0


def test_waituntil_polls_with_the_clock_and_times_out():
    clock = ManualClock()
    ready_at = 0.35

    def ready() -> bool:
        return clock.now() >= ready_at

    interp = run(
        r"""WaitUntil Ready() \PollRate:=0.1;
        WaitUntil FALSE \MaxTime:=1 \TimeFlag:=late;
        WaitUntil FALSE \MaxTime:=0.5;
        ERROR
          IF ERRNO = ERR_WAIT_MAXTIME s := "timed out";
          RETURN;""",
        data="VAR bool late; VAR string s;",
        builtins={"Ready": ready},
        clock=clock,
    )
    assert (
        clock.sleeps[:4] == pytest.approx([0.1] * 4) and interp.get("late") is True and interp.get("s") == "timed out"
    )


SERVER = r"""
MODULE SerialServer
  ! command frames: USINT cmd, Float4 value; reply: USINT status
  VAR iodev com;
  VAR rawbytes buf;
  VAR num cmd;
  VAR num value;
  VAR num served;
  VAR num timeouts;
  VAR jointtarget jt;

  PROC main()
    Open "COM1:", com \Bin;
    WHILE TRUE DO
      ClearRawBytes buf;
      ReadRawBytes com, buf, 5 \Time:=0.05;
      UnpackRawBytes buf, 1, cmd \IntX:=USINT;
      UnpackRawBytes buf, 2, value \Float4;
      TEST cmd
      CASE 1:
        jt := CJointT();
        jt.robax.rax_1 := value;
        MoveAbsJ jt, v100, fine, tool0;
        Reply 0;
      CASE 2:
        EXIT;
      DEFAULT:
        Reply 1;
      ENDTEST
      Incr served;
    ENDWHILE
  ERROR
    IF ERRNO = ERR_DEV_MAXTIME THEN
      Incr timeouts;
      RETRY;
    ENDIF
    RAISE;
  ENDPROC

  PROC Reply(num status)
    ClearRawBytes buf;
    PackRawBytes status, buf, 1 \IntX:=USINT;
    WriteRawBytes com, buf;
  ENDPROC
ENDMODULE
"""


def test_a_serial_server_module_runs_against_emulated_builtins():
    incoming = [None, None, struct.pack("<Bf", 1, 30.0), struct.pack("<Bf", 7, 0.0), None, struct.pack("<Bf", 2, 0)]
    sent, moves, joints = [], [], [0.0] * 6
    reg = Builtins()

    @reg.register()
    def Open(name, dev, Bin=False):  # noqa: N802,N803 - RAPID names
        dev.value = {"port": name, "binary": Bin}

    @reg.register()
    def ReadRawBytes(dev, raw, count, Time=None):  # noqa: N802,N803
        frame = incoming.pop(0)
        if frame is None:
            raise RapidError("ERR_DEV_MAXTIME")
        raw.write(1, frame[: int(count)])

    reg.add("WriteRawBytes", lambda dev, raw: sent.append(bytes(raw)))
    reg.add("CJointT", lambda: make_value("jointtarget", [joints, [9e9] * 6]))

    @reg.register()
    def MoveAbsJ(target, speed, zone, tool, **options):  # noqa: N802
        moves.append((target.robax.to_list(), speed.v_tcp, zone.finep, options))
        joints[:] = target.robax.to_list()

    interp = Interpreter(SERVER, reg)
    assert interp.run() == "exit"
    assert interp.get("com").value == {"port": "COM1:", "binary": True}
    assert moves == [([30.0, 0, 0, 0, 0, 0], 100, True, {})] and sent == [b"\x00", b"\x01"]
    assert interp.get("served") == 2 and interp.get("timeouts") == 3 and incoming == []


def test_interpreter_implements_the_runtime_contract_its_parts_are_typed_against():
    from maniskill_irb120.abb.emulator.rapid.contract import Runtime

    assert isinstance(Interpreter("MODULE M\nENDMODULE"), Runtime)
    parts = Path(__file__).resolve().parents[3] / "maniskill_irb120/abb/emulator/rapid"
    for part in ("statements.py", "calls.py", "expressions.py", "frames.py", "contract.py"):
        assert "rapid.interpreter import" not in (parts / part).read_text(), part


def test_num_is_a_32_bit_float():
    """docs/reference.md: num is a 32-bit float, exact integers up to 2^23 and then in steps: 16777216 + 1 is 16777216,
    0.1 is stored as float32(0.1); a dnum keeps the double; a value beyond float32's range stops the program."""
    src = """MODULE M
    VAR num a := 0;
    VAR num b := 0;
    VAR num c := 8388607;
    VAR dnum d := 0;
    VAR bool same := FALSE;
    VAR bool literal := FALSE;
    PROC main()
        a := 16777216 + 1;
        b := 0.1;
        literal := b = 0.1;
        c := c + 1;
        d := 16777217;
        same := 16777216 + 1 = 16777216;
    ENDPROC
    PROC huge()
        a := 1E38 * 10;
    ENDPROC
ENDMODULE
"""
    interp = Interpreter(src)
    interp.run("main")
    assert interp.get("a") == 16777216.0 and interp.get("same") is True
    assert interp.get("b") == struct.unpack("<f", struct.pack("<f", 0.1))[0] != 0.1
    assert interp.get("literal") is True  # a literal is a num too
    assert interp.get("c") == 8388608.0  # 2^23: still exact
    assert interp.get("d") == 16777217.0
    with pytest.raises(RapidRuntimeError, match="outside the range of a num"):
        interp.call("huge")
