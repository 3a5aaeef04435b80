MODULE IRB120Serial
    !
    ! The serial channel of the maniskill_irb120 RAPID server (IRB120Server.mod): Open, ReadRawBytes,
    ! UnpackRawBytes, WriteBin, ClearIOBuff on one of the controller's serial ports. Needs no RobotWare option. Load it beside
    ! IRB120Server.mod, never together with IRB120Socket.mod (both provide the same routines).
    !
    ! Global (called by IRB120Server.mod): IRB120ChanOpen, IRB120ChanRead, IRB120ChanWrite, IRB120ChanNewPeer,
    ! IRB120ChanReopen, IRB120ChanClose. Everything else is LOCAL.
    !
    ! The port, as named in the controller's SIO configuration (its baud rate is set there: 19200 or more)
    LOCAL CONST string SER_CHANNEL := "COM1:";
    LOCAL VAR iodev serDev;
    LOCAL VAR rawbytes serRaw;

    PROC IRB120ChanOpen()
        Open SER_CHANNEL, serDev\Bin;
        ClearIOBuff serDev;
    ENDPROC

    FUNC num IRB120ChanRead(VAR byte data{*}, num first, num count, num timeout)
        ! count bytes into data{first} .. data{first + count - 1}, read in one call: count when all came within
        ! timeout seconds, else -1 (what did come is not relied on: the server scans for the next sync). A serial
        ! line never closes: never -2
        ReadRawBytes serDev, serRaw\NoOfBytes:=count\Time:=timeout;
        FOR i FROM 1 TO count DO
            UnpackRawBytes serRaw, i, data{first + i - 1}\Hex1;
        ENDFOR
        RETURN count;
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
        ClearIOBuff serDev;
    ENDPROC

    PROC IRB120ChanClose()
        ! the server's UNDO (PP to main): the next start opens the port again
        Close serDev;
    ENDPROC
ENDMODULE
