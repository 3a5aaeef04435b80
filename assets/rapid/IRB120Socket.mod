MODULE IRB120Socket
    !
    ! The TCP channel of the maniskill_irb120 RAPID server (IRB120Server.mod): one client at a time on
    ! SOCK_ADDRESS:SOCK_PORT. Needs RobotWare option 616-1 PC Interface or 672-1 Socket Messaging (the socket
    ! API's names are resolved when the module loads). Load it beside IRB120Server.mod, never together with
    ! IRB120Serial.mod (both provide the same routines).
    !
    ! Global (called by IRB120Server.mod): IRB120ChanOpen, IRB120ChanRead, IRB120ChanWrite, IRB120ChanNewPeer,
    ! IRB120ChanReopen, IRB120ChanClose. Everything else is LOCAL.
    !
    ! Only the PC at PC_ADDRESS is served: a client from any other address is closed at once and logged (a robot
    ! command port open to the whole cell network is what integrators are warned against). Set it to your PC's.
    LOCAL CONST string PC_ADDRESS := "192.168.125.2";
    !
    ! The client is on one of two sockets (sockCur): a new client that connects while the current one is silent
    ! (a PC that crashed without closing: a half-open connection only times out) is accepted on the other one.
    LOCAL CONST string SOCK_ADDRESS := "192.168.125.1";
    LOCAL CONST num SOCK_PORT := 5000;
    ! how long IRB120ChanNewPeer waits for a new client (s)
    LOCAL CONST num SOCK_POLL_S := 0.1;
    ! how long a client the server turns to may stay quiet for its old bytes to count as all drained (s; verify: the
    ! shortest \Time SocketReceive honours)
    LOCAL CONST num DRAIN_S := 0.02;
    LOCAL CONST num DRAIN_READS := 20;
    LOCAL VAR socketdev sockListen;
    LOCAL VAR socketdev sockA;
    LOCAL VAR socketdev sockB;
    ! the bytes of the last SocketReceive: sockRaw's bytes sockNext..sockLen are not handed to the server yet
    LOCAL VAR rawbytes sockRaw;
    LOCAL VAR num sockNext := 1;
    LOCAL VAR num sockLen := 0;
    LOCAL VAR num sockCur := 1;
    LOCAL VAR bool sockPending := FALSE;

    PROC IRB120ChanOpen()
        SocketCreate sockListen;
        SocketBind sockListen, SOCK_ADDRESS, SOCK_PORT;
        SocketListen sockListen;
        sockCur := 1;
        sockPending := FALSE;
        sockNext := 1;
        sockLen := 0;
        AcceptPc sockA;
    ENDPROC

    LOCAL FUNC bool FromPc(VAR socketdev client, string peer)
        ! the client just accepted is the PC at PC_ADDRESS; any other is closed and logged
        IF peer = PC_ADDRESS RETURN TRUE;
        SocketClose client;
        ErrWrite\W, "IRB120Socket: client refused", "a connection from " + peer + " is not PC_ADDRESS " + PC_ADDRESS;
        RETURN FALSE;
    ENDFUNC

    LOCAL PROC AcceptPc(VAR socketdev client)
        ! wait for a connection from PC_ADDRESS
        VAR string peer;
        WHILE TRUE DO
            SocketAccept sockListen, client\ClientAddress:=peer\Time:=WAIT_MAX;
            IF FromPc(client, peer) RETURN;
        ENDWHILE
    ENDPROC

    LOCAL FUNC bool PollPc(VAR socketdev client)
        ! a connection from PC_ADDRESS within SOCK_POLL_S?
        VAR string peer;
        SocketAccept sockListen, client\ClientAddress:=peer\Time:=SOCK_POLL_S;
        RETURN FromPc(client, peer);
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT RETURN FALSE;
        RAISE;
    ENDFUNC

    FUNC num IRB120ChanRead(VAR byte data{*}, num first, num room, num timeout)
        ! the bytes that have come (at least one, at most room) into data{first..}: how many; -1 when none came within
        ! timeout seconds; -2 when the client closed the connection. Bytes received beyond room are kept for the
        ! next call: none is lost, so the server can resynchronise without losing the frame behind a corrupted one
        VAR num n;
        IF sockNext > sockLen THEN
            IF sockCur = 1 THEN
                SocketReceive sockA\RawData:=sockRaw\Time:=timeout;
            ELSE
                SocketReceive sockB\RawData:=sockRaw\Time:=timeout;
            ENDIF
            sockNext := 1;
            sockLen := RawBytesLen(sockRaw);
        ENDIF
        n := sockLen - sockNext + 1;
        IF n > room n := room;
        ! (FOR counts down when its end is below its start: nothing to hand over is never a loop)
        IF n < 1 RETURN -1;
        FOR i FROM 1 TO n DO
            UnpackRawBytes sockRaw, sockNext + i - 1, data{first + i - 1}\Hex1;
        ENDFOR
        sockNext := sockNext + n;
        RETURN n;
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT RETURN -1;
        IF ERRNO = ERR_SOCK_CLOSED RETURN -2;
        RAISE;
    ENDFUNC

    FUNC bool IRB120ChanWrite(byte data{*}, num count)
        ! the first count bytes of data; FALSE when the client is gone
        IF sockCur = 1 THEN
            SocketSend sockA\Data:=data\NoOfBytes:=count;
        ELSE
            SocketSend sockB\Data:=data\NoOfBytes:=count;
        ENDIF
        RETURN TRUE;
    ERROR
        IF ERRNO = ERR_SOCK_CLOSED RETURN FALSE;
        RAISE;
    ENDFUNC

    FUNC bool IRB120ChanNewPeer()
        ! a new client is waiting? (accepted on the spare socket; IRB120ChanReopen serves it)
        IF NOT sockPending THEN
            IF sockCur = 1 THEN
                sockPending := PollPc(sockB);
            ELSE
                sockPending := PollPc(sockA);
            ENDIF
        ENDIF
        RETURN sockPending;
    ENDFUNC

    PROC IRB120ChanReopen()
        ! drop the current client and what it sent; serve the one waiting, or wait for the next. The next client's
        ! bytes from before the server turned to it are dropped (Drained): they were sent while another client held
        ! the robot, or by a client that has closed since, and never become motion. A client that has closed is
        ! passed over. The client's connect resends its HELLO until it is answered (docs/protocol.md).
        sockNext := 1;
        sockLen := 0;
        IF sockCur = 1 THEN
            SocketClose sockA;
            IF NOT sockPending AcceptPc sockB;
            WHILE NOT Drained(sockB) DO
                AcceptPc sockB;
            ENDWHILE
            sockCur := 2;
        ELSE
            SocketClose sockB;
            IF NOT sockPending AcceptPc sockA;
            WHILE NOT Drained(sockA) DO
                AcceptPc sockA;
            ENDWHILE
            sockCur := 1;
        ENDIF
        sockPending := FALSE;
    ENDPROC

    LOCAL FUNC bool Drained(VAR socketdev client)
        ! reads and drops what the client sent before the server turned to it: TRUE once it has been quiet for
        ! DRAIN_S (or after DRAIN_READS reads: a client that never pauses is served, its next bytes read as frames);
        ! FALSE when it has closed (it is closed here too)
        FOR i FROM 1 TO DRAIN_READS DO
            SocketReceive client\RawData:=sockRaw\Time:=DRAIN_S;
        ENDFOR
        RETURN TRUE;
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT RETURN TRUE;
        IF ERRNO = ERR_SOCK_CLOSED THEN
            SocketClose client;
            RETURN FALSE;
        ENDIF
        RAISE;
    ENDFUNC

    PROC IRB120ChanClose()
        ! the server's UNDO (PP to main): every socket closed; the next start listens afresh
        SocketClose sockA;
        SocketClose sockB;
        SocketClose sockListen;
        sockPending := FALSE;
        sockNext := 1;
        sockLen := 0;
    ENDPROC
ENDMODULE
