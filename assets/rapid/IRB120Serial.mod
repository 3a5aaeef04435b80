MODULE IRB120Serial
    !
    ! The serial channel of the maniskill_irb120 RAPID server (IRB120Server.mod): Open, ReadRawBytes,
    ! UnpackRawBytes, WriteBin, ClearIOBuff, RawBytesLen on one of the controller's serial ports. Needs no RobotWare option. Load it beside
    ! IRB120Server.mod, never together with IRB120Socket.mod (both provide the same routines).
    !
    ! Global (called by IRB120Server.mod): IRB120ChanOpen, IRB120ChanRead, IRB120ChanWrite, IRB120ChanNewPeer,
    ! IRB120ChanReopen, IRB120ChanClose. Everything else is LOCAL.
    !
    ! The port, as named in the controller's SIO configuration (its baud rate is set there: 19200 or more)
    LOCAL CONST string SER_CHANNEL := "COM1:";
    LOCAL VAR iodev serDev;
    ! the bytes of the last ReadRawBytes: serRaw's bytes serNext..serLen are not handed to the server yet
    LOCAL VAR rawbytes serRaw;
    LOCAL VAR num serNext := 1;
    LOCAL VAR num serLen := 0;

    PROC IRB120ChanOpen()
        Open SER_CHANNEL, serDev\Bin;
        DropInput;
    ENDPROC

    LOCAL PROC DropInput()
        ! every byte received and not yet read is dropped: those in the device's input buffer (ClearIOBuff) and those
        ! read but not handed to the server. Bytes the PC sent while the program was stopped never become commands.
        ClearIOBuff serDev;
        serNext := 1;
        serLen := 0;
    ENDPROC

    FUNC num IRB120ChanRead(VAR byte data{*}, num first, num room, num timeout)
        ! the bytes that have come (at least one, at most room) into data{first..}: how many; -1 when none came within
        ! timeout seconds. Bytes read from the device beyond room are kept for the next call: none is lost, so the
        ! server can resynchronise after a corrupted frame without losing the frame behind it. A serial line never
        ! closes: never -2
        VAR num n;
        IF serNext > serLen THEN
            ReadRawBytes serDev, serRaw\Time:=timeout;
            serNext := 1;
            serLen := RawBytesLen(serRaw);
        ENDIF
        n := serLen - serNext + 1;
        IF n > room n := room;
        ! (FOR counts down when its end is below its start: nothing to hand over is never a loop)
        IF n < 1 RETURN -1;
        FOR i FROM 1 TO n DO
            UnpackRawBytes serRaw, serNext + i - 1, data{first + i - 1}\Hex1;
        ENDFOR
        serNext := serNext + n;
        RETURN n;
    ERROR
        IF ERRNO = ERR_DEV_MAXTIME RETURN -1;
        RAISE;
    ENDFUNC

    FUNC bool IRB120ChanWrite(byte data{*}, num count)
        ! the first count bytes of data; FALSE when the peer is gone (never on a serial line)
        WriteBin serDev, data, count;
        RETURN TRUE;
    ENDFUNC

    FUNC bool IRB120ChanNewPeer()
        ! a new peer is waiting to be served? A serial line has one peer: never
        RETURN FALSE;
    ENDFUNC

    PROC IRB120ChanReopen()
        ! start over with the peer: drop what is buffered
        DropInput;
    ENDPROC

    PROC IRB120ChanClose()
        ! the server's UNDO (PP to main): the next start opens the port again
        Close serDev;
    ENDPROC
ENDMODULE
