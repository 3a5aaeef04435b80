MODULE IRB120Server
    !
    ! maniskill_irb120 RAPID server for an ABB IRB 120 on an IRC5: serves the wire protocol of
    ! docs/protocol.md (frames: sync 0xA5, length, type, sequence, payload, CRC-16/CCITT-FALSE) on ONE channel.
    ! This core module names no option's instruction: it reads and writes through a channel module loaded beside it,
    ! IRB120Serial.mod (serial, no RobotWare option) or IRB120Socket.mod (TCP, 616-1 PC Interface or 672-1 Socket
    ! Messaging), which provides the global routines IRB120ChanOpen, IRB120ChanRead, IRB120ChanWrite,
    ! IRB120ChanNewPeer and IRB120ChanReopen. The world zone around the workspace is the system module
    ! IRB120Zone.sys (608-1 World Zones), installed at power on. See docs/real_robot.md.
    !
    ! Everything here is LOCAL except the entry routine IRB120Server (set the task's main entry to it, or call it
    ! from the stock MainModule's main) and the RESTART event routine IRB120ServerRestart (Controller > Event
    ! Routine: Restart; it tells the server the program was stopped and started again without PP to main).
    !
    ! Every command is checked here before anything moves, whatever the PC does: frame integrity (a resynchronising
    ! scan: a corrupted frame costs only itself), the sequence number (a repeated frame is answered again, never executed twice), per-step limits, the
    ! workspace box, reachability and joint limits (CalcJointT in an ERROR handler), joint speed, the operating mode
    ! (motion only in manual reduced speed unless ALLOW_AUTO). A heartbeat
    ! watchdog stops and holds the robot when no valid frame arrives within HEARTBEAT_S while it moves. After the
    ! program was stopped (emergency stop, enabling device, Stop) and started again without PP to main, the robot
    ! is held and every motion command refused (E_RESTARTED) until the PC opens a new session (a HELLO the server
    ! accepts; a refused one changes nothing). Gripper bytes the protocol does not define are refused (E_BAD_VALUE).
    ! Refusals, watchdog stops, restarts and new connections are written to the event log (ErrWrite).
    !
    ! Units on the wire: tool steps 0.01 mm and 0.001 deg, joints 0.02 deg, TCP position 0.05 mm.
    !
    ! ---------------------------------------------------------------- configuration (see docs/real_robot.md)
    LOCAL CONST string GRIPPER_SIGNAL := "doGripperOpen";
    LOCAL CONST string MOTORS_ON_SIGNAL := "doMotorsOn";
    LOCAL CONST string ESTOP_SIGNAL := "doEmergencyStop";
    LOCAL CONST num HEARTBEAT_S := 0.5;
    ! a client silent this long (s) gives way to a new client waiting on the channel (TCP: a PC that crashed)
    LOCAL CONST num SILENCE_S := 1;
    ! the rest of a frame must come within FRAME_S of its sync (while the robot moves, also before the watchdog is
    ! due), or its sync is dropped and the scan resumes at the byte after it: a truncated frame, or a corrupted length
    ! byte claiming more than came, costs at most this. The longest frame takes 40 ms at 9600 baud.
    LOCAL CONST num FRAME_S := 0.5;
    ! a motion is over once every axis is this close to its target (deg): status MOVING -> IDLE
    LOCAL CONST num ARRIVED_DEG := 0.05;
    ! the safety envelope (the PC checks the same numbers: maniskill_irb120/abb/envelope.py)
    LOCAL CONST num STEP_POS_MM := 10;
    LOCAL CONST num STEP_ROT_DEG := 10;
    LOCAL CONST pos WORKSPACE_LOW := [150, -320, 10];
    LOCAL CONST pos WORKSPACE_HIGH := [600, 320, 450];
    LOCAL CONST num JOINT_LOW{6} := [-165, -110, -110, -160, -120, -400];
    LOCAL CONST num JOINT_HIGH{6} := [165, 110, 70, 160, 120, 400];
    ! ABB's axis speeds (250, 250, 250, 320, 320, 420 deg/s) over one 50 ms control period
    LOCAL CONST num JOINT_STEP_DEG{6} := [12.5, 12.5, 12.5, 16, 16, 21];
    !
    ! The TCP of the MetalWork gripper, 57 mm out of the flange; its x axis (the approach axis of the
    ! action space) is tool0's z axis, its z axis (camera side) is tool0's -x axis.
    LOCAL PERS tooldata tGripper := [TRUE, [[0, 0, 57], [0.707107, 0, -0.707107, 0]], [0.6, [0, 0, 30], [1, 0, 0, 0], 0, 0, 0]];
    ! A full step (10 mm or 10 deg) at vFull (250 mm/s and 250 deg/s) takes 40 ms, inside the 50 ms control period;
    ! zone z1 lets consecutive steps blend, so the program answers as soon as the step is planned.
    LOCAL CONST speeddata vFull := [250, 250, 5000, 1000];
    ! Every motion runs at SPEED_PERCENT of vFull (TCP and reorientation speed). For the first runs of a cell set
    ! it to 50: a full step then takes 80 ms and the robot lags the policy rather than keeping up with it; back to
    ! 100 once the cell has been proven (docs/real_robot.md).
    LOCAL CONST num SPEED_PERCENT := 100;
    LOCAL VAR speeddata vStep;
    LOCAL CONST zonedata zStep := z1;
    ! The reset (RESET): one joint move, validated along its whole path, at a low speed, ending at a stop point.
    ! The PC waits for its reply as long as the move takes (maniskill_irb120/abb/protocol.py RESET_TCP_MM_S, keep
    ! them in step).
    LOCAL CONST speeddata vReset := [100, 45, 5000, 1000];
    ! points checked along the reset's joint path (each TCP inside the workspace box)
    LOCAL CONST num RESET_CHECKS := 10;
    !
    ! Motion only in manual reduced speed (OpMode() = OP_MAN_PROG: TCP at most 250 mm/s, the operator holding the
    ! enabling device): in OP_AUTO or OP_MAN_TEST (manual full speed) every motion command is refused with
    ! E_OPERATING_MODE, so a policy never runs unattended by default. An integrator sets this TRUE deliberately, after
    ! a risk assessment of the cell for unattended operation (docs/real_robot.md).
    LOCAL CONST bool ALLOW_AUTO := FALSE;
    !
    ! ---------------------------------------------------------------- protocol constants
    LOCAL CONST num SYNC := 165;
    LOCAL CONST num MAX_PAYLOAD := 32;
    LOCAL CONST num T_STATE := 1;
    LOCAL CONST num T_TOOL_STEP := 2;
    LOCAL CONST num T_JOINTS := 3;
    LOCAL CONST num T_GRIPPER := 4;
    LOCAL CONST num T_STOP := 5;
    LOCAL CONST num T_HELLO := 6;
    LOCAL CONST num T_RESET := 7;
    ! the protocol version a HELLO must carry (docs/protocol.md)
    LOCAL CONST num PROTOCOL_VERSION := 1;
    ! a frame whose type has this bit set is a reply (a line echoing the controller's own frames): dropped
    LOCAL CONST num T_REPLY := 128;
    LOCAL CONST num S_IDLE := 0;
    LOCAL CONST num S_MOVING := 1;
    LOCAL CONST num S_HELD := 2;
    LOCAL CONST num S_FAULT := 3;
    LOCAL CONST num E_OK := 0;
    LOCAL CONST num E_STEP_LIMIT := 1;
    LOCAL CONST num E_WORKSPACE := 2;
    LOCAL CONST num E_UNREACHABLE := 3;
    LOCAL CONST num E_JOINT_LIMIT := 4;
    LOCAL CONST num E_BAD_LENGTH := 5;
    LOCAL CONST num E_UNKNOWN_TYPE := 6;
    LOCAL CONST num E_WATCHDOG := 7;
    LOCAL CONST num E_MOTORS_OFF := 8;
    LOCAL CONST num E_ESTOP := 9;
    LOCAL CONST num E_JOINT_SPEED := 10;
    LOCAL CONST num E_OPERATING_MODE := 11;
    LOCAL CONST num E_RESTARTED := 12;
    LOCAL CONST num E_VERSION := 13;
    LOCAL CONST num E_BAD_VALUE := 14;
    !
    ! CRC-16/CCITT-FALSE, table-driven (poly 0x1021): entry i is the CRC register after shifting byte i through
    ! it, split into its high and low byte (BitXOr works on bytes). Three statements a byte instead of ~50.
    LOCAL CONST byte CRC_HI{256} := [
        0, 16, 32, 48, 64, 80, 96, 112, 129, 145, 161, 177, 193, 209, 225, 241, 18, 2, 50, 34, 82, 66, 114, 98,
        147, 131, 179, 163, 211, 195, 243, 227, 36, 52, 4, 20, 100, 116, 68, 84, 165, 181, 133, 149, 229, 245, 197, 213,
        54, 38, 22, 6, 118, 102, 86, 70, 183, 167, 151, 135, 247, 231, 215, 199, 72, 88, 104, 120, 8, 24, 40, 56,
        201, 217, 233, 249, 137, 153, 169, 185, 90, 74, 122, 106, 26, 10, 58, 42, 219, 203, 251, 235, 155, 139, 187, 171,
        108, 124, 76, 92, 44, 60, 12, 28, 237, 253, 205, 221, 173, 189, 141, 157, 126, 110, 94, 78, 62, 46, 30, 14,
        255, 239, 223, 207, 191, 175, 159, 143, 145, 129, 177, 161, 209, 193, 241, 225, 16, 0, 48, 32, 80, 64, 112, 96,
        131, 147, 163, 179, 195, 211, 227, 243, 2, 18, 34, 50, 66, 82, 98, 114, 181, 165, 149, 133, 245, 229, 213, 197,
        52, 36, 20, 4, 116, 100, 84, 68, 167, 183, 135, 151, 231, 247, 199, 215, 38, 54, 6, 22, 102, 118, 70, 86,
        217, 201, 249, 233, 153, 137, 185, 169, 88, 72, 120, 104, 24, 8, 56, 40, 203, 219, 235, 251, 139, 155, 171, 187,
        74, 90, 106, 122, 10, 26, 42, 58, 253, 237, 221, 205, 189, 173, 157, 141, 124, 108, 92, 76, 60, 44, 28, 12,
        239, 255, 207, 223, 175, 191, 143, 159, 110, 126, 78, 94, 46, 62, 14, 30];
    LOCAL CONST byte CRC_LO{256} := [
        0, 33, 66, 99, 132, 165, 198, 231, 8, 41, 74, 107, 140, 173, 206, 239, 49, 16, 115, 82, 181, 148, 247, 214,
        57, 24, 123, 90, 189, 156, 255, 222, 98, 67, 32, 1, 230, 199, 164, 133, 106, 75, 40, 9, 238, 207, 172, 141,
        83, 114, 17, 48, 215, 246, 149, 180, 91, 122, 25, 56, 223, 254, 157, 188, 196, 229, 134, 167, 64, 97, 2, 35,
        204, 237, 142, 175, 72, 105, 10, 43, 245, 212, 183, 150, 113, 80, 51, 18, 253, 220, 191, 158, 121, 88, 59, 26,
        166, 135, 228, 197, 34, 3, 96, 65, 174, 143, 236, 205, 42, 11, 104, 73, 151, 182, 213, 244, 19, 50, 81, 112,
        159, 190, 221, 252, 27, 58, 89, 120, 136, 169, 202, 235, 12, 45, 78, 111, 128, 161, 194, 227, 4, 37, 70, 103,
        185, 152, 251, 218, 61, 28, 127, 94, 177, 144, 243, 210, 53, 20, 119, 86, 234, 203, 168, 137, 110, 79, 44, 13,
        226, 195, 160, 129, 102, 71, 36, 5, 219, 250, 153, 184, 95, 126, 29, 60, 211, 242, 145, 176, 87, 118, 21, 52,
        76, 109, 14, 47, 200, 233, 138, 171, 68, 101, 6, 39, 192, 225, 130, 163, 125, 92, 63, 30, 249, 216, 187, 154,
        117, 84, 55, 22, 241, 208, 179, 146, 46, 15, 108, 77, 170, 139, 232, 201, 38, 7, 100, 69, 162, 131, 224, 193,
        31, 62, 93, 124, 155, 186, 217, 248, 23, 54, 85, 116, 147, 178, 209, 240];
    !
    ! ---------------------------------------------------------------- state
    LOCAL VAR signaldo doGripper;
    LOCAL VAR signaldo doMotors;
    LOCAL VAR signaldo doEstop;
    ! the receive buffer: rx{rxFirst..rxLast} came from the channel and is not consumed yet. A frame candidate starts
    ! at rx{frm} (its sync; 0: none), so rx{frm + 1} is its length, rx{frm + 2} its type, rx{frm + 3} its sequence
    ! number and rx{frm + 4} its first payload byte. RX_SIZE (rx's size) holds the longest frame (38 bytes) and a read
    ! of what came after it.
    LOCAL CONST num RX_SIZE := 96;
    LOCAL VAR byte rx{96};
    LOCAL VAR num rxFirst := 1;
    LOCAL VAR num rxLast := 0;
    LOCAL VAR num frm := 0;
    LOCAL VAR byte tx{40};
    LOCAL VAR num txLen := 0;
    ! the duplicate cache: the last command executed (sequence number, type, CRC); its reply is still in tx.
    ! Cleared whenever a connection (re)opens: a new peer's sequence numbers are its own.
    LOCAL VAR num lastSeq := -1;
    LOCAL VAR num lastKind := -1;
    LOCAL VAR num lastCrc := -1;
    LOCAL VAR num status := 0;
    ! the gripper output the commands so far ask for: DOutput, or what a MoveLDO queued will set it to
    LOCAL VAR num gripCmd := 1;
    LOCAL VAR bool watchdogFired := FALSE;
    LOCAL VAR num refusal := 0;
    LOCAL VAR num lastLogged := 0;
    ! set by the RESTART event routine: the program was stopped and started again where it stood
    LOCAL VAR bool restarted := FALSE;
    LOCAL VAR bool restartHeld := FALSE;
    ! time since the last valid frame (the watchdog's), since the last read (the silence before a new peer) and since
    ! the frame candidate's sync was found (its frame time)
    LOCAL VAR clock clkValid;
    LOCAL VAR clock clkHeard;
    LOCAL VAR clock clkFrame;
    ! where the controller is taking the TCP (the last motion queued; where it stands once still): the reply
    ! carries it, so the PC knows every pose a next step could be taken from (docs/protocol.md)
    LOCAL VAR robtarget lastTarget;
    LOCAL VAR jointtarget lastJoints;

    PROC IRB120Server()
        ! the entry routine: the task's main entry, or called from MainModule's main
        InitServer;
        WHILE TRUE DO
            ServeOneFrame;
        ENDWHILE
    UNDO
        ! PP to main while the server runs: the channel is closed, so the next start opens it afresh
        IRB120ChanClose;
    ENDPROC

    PROC IRB120ServerRestart()
        ! the task's RESTART event routine: runs when the program starts again where it was stopped (the
        ! controller's path planner goes on with the path it had queued); the server holds the robot next
        restarted := TRUE;
    ENDPROC

    LOCAL PROC InitServer()
        AliasIO GRIPPER_SIGNAL, doGripper;
        AliasIO MOTORS_ON_SIGNAL, doMotors;
        AliasIO ESTOP_SIGNAL, doEstop;
        gripCmd := DOutput(doGripper);
        ConfL\Off;
        SingArea\Wrist;
        vStep := vFull;
        vStep.v_tcp := vFull.v_tcp * SPEED_PERCENT / 100;
        vStep.v_ori := vFull.v_ori * SPEED_PERCENT / 100;
        lastTarget := CRobT(\Tool:=tGripper\WObj:=wobj0);
        lastJoints := CJointT();
        status := S_IDLE;
        watchdogFired := FALSE;
        restarted := FALSE;
        restartHeld := FALSE;
        IRB120ChanOpen;
        NewSession;
    ENDPROC

    LOCAL PROC NewSession()
        ! a connection (re)opened: nothing of the previous peer's is answered to this one or run for it, and a
        ! watchdog stop of the previous peer's is not held against it (the robot is held: its replies say HELD)
        ClearCache;
        watchdogFired := FALSE;
        rxFirst := 1;
        rxLast := 0;
        frm := 0;
        RestartClock clkValid;
        RestartClock clkHeard;
    ENDPROC

    LOCAL PROC StartSession()
        ! an accepted HELLO: the PC has learned of a restart or a watchdog stop (the reply's status says HELD), and
        ! nothing it sent before is answered from the cache
        ClearCache;
        watchdogFired := FALSE;
        restartHeld := FALSE;
        lastLogged := E_OK;
    ENDPROC

    LOCAL PROC ClearCache()
        lastSeq := -1;
        lastKind := -1;
        lastCrc := -1;
    ENDPROC

    LOCAL PROC RestartClock(VAR clock c)
        ClkReset c;
        ClkStart c;
    ENDPROC

    LOCAL PROC Reconnect()
        ! the peer went away, or gives way to a new one: hold the robot, then serve the next peer
        HoldRobot\Quick;
        ErrWrite\I, "IRB120Server: peer replaced", "the robot is held; serving the next peer";
        IRB120ChanReopen;
        NewSession;
    ENDPROC

    LOCAL PROC CheckRestart()
        ! after a stop and a start without PP to main: hold the robot (the planner may be finishing the path it had
        ! queued) and refuse motion until the PC opens a new session (an accepted HELLO), so commands it sent before the
        ! stop never run
        IF restarted THEN
            restarted := FALSE;
            HoldRobot\Quick;
            restartHeld := TRUE;
            ErrWrite\W, "IRB120Server: restarted", "the program was stopped and started again: robot held";
        ENDIF
    ENDPROC

    LOCAL PROC HoldRobot(\switch Quick)
        IF Present(Quick) THEN
            StopMove\Quick;
        ELSE
            StopMove;
        ENDIF
        ClearPath;
        StartMove;
        ! a gripper change tied to the path just dropped never happens
        gripCmd := DOutput(doGripper);
        lastTarget := CRobT(\Tool:=tGripper\WObj:=wobj0);
        IF status <> S_FAULT status := S_HELD;
    ENDPROC

    ! ---------------------------------------------------------------- receiving
    LOCAL FUNC num ReadMore(num timeout)
        ! appends what the channel has (waiting at most timeout s for the first byte) to rx: how many bytes came; -1
        ! none within timeout; -2 the peer went away (the robot is held and the next peer is being served)
        VAR num got;
        IF rxFirst > rxLast THEN
            rxFirst := 1;
            rxLast := 0;
        ELSEIF RX_SIZE - rxLast < MAX_PAYLOAD + 6 THEN
            CompactRx;
        ENDIF
        got := IRB120ChanRead(rx, rxLast + 1, RX_SIZE - rxLast, timeout);
        IF got > 0 THEN
            rxLast := rxLast + got;
            RestartClock clkHeard;
        ELSEIF got < -1 THEN
            Reconnect;
        ENDIF
        RETURN got;
    ENDFUNC

    LOCAL PROC CompactRx()
        ! rx{rxFirst..rxLast} to the front (at most a frame candidate's 37 bytes: room for the next read)
        VAR num k;
        k := rxFirst - 1;
        FOR i FROM rxFirst TO rxLast DO
            rx{i - k} := rx{i};
        ENDFOR
        rxLast := rxLast - k;
        rxFirst := 1;
        IF frm > 0 frm := frm - k;
    ENDPROC

    LOCAL FUNC num WaitTime()
        ! how long a read may wait: until the watchdog is due while the robot moves, else one heartbeat
        VAR num t;
        t := HEARTBEAT_S;
        IF status = S_MOVING THEN
            t := HEARTBEAT_S - ClkRead(clkValid);
            IF t < 0.01 t := 0.01;
        ENDIF
        RETURN t;
    ENDFUNC

    LOCAL FUNC num FrameWait()
        ! how long to wait for more of the frame candidate: until FRAME_S after its sync, and while the robot moves no
        ! longer than the watchdog allows (a frame under way never delays a watchdog stop)
        VAR num t;
        t := FRAME_S - ClkRead(clkFrame);
        IF status = S_MOVING AND t > WaitTime() t := WaitTime();
        IF t < 0.01 t := 0.01;
        RETURN t;
    ENDFUNC

    LOCAL FUNC bool SkipToSync()
        ! rxFirst to the next sync in rx: TRUE; FALSE when rx has none (every byte before it is noise)
        WHILE rxFirst <= rxLast DO
            IF rx{rxFirst} = SYNC RETURN TRUE;
            rxFirst := rxFirst + 1;
        ENDWHILE
        RETURN FALSE;
    ENDFUNC

    LOCAL FUNC bool NextFrame()
        ! the next frame whose CRC checks: TRUE, it starts at rx{frm}; FALSE, nothing came within WaitTime (or the
        ! peer was replaced). A sync whose length byte is over MAX_PAYLOAD, whose CRC fails or whose rest does not
        ! come within FRAME_S is dropped alone: the scan resumes at the byte after it, with every byte that
        ! came after it kept, so a corrupted frame never swallows the valid frame behind it. The watchdog is checked
        ! at every turn: noise, or a frame under way, never keeps a moving robot going.
        VAR num need;
        WHILE TRUE DO
            IF ClkRead(clkValid) >= HEARTBEAT_S Watchdog;
            IF SkipToSync() THEN
                IF frm <> rxFirst THEN
                    ! a new candidate: its frame time starts now
                    frm := rxFirst;
                    RestartClock clkFrame;
                ENDIF
                need := 2;
                IF rxLast > frm THEN
                    need := rx{frm + 1} + 6;
                    IF need > MAX_PAYLOAD + 6 THEN
                        need := 0;
                    ELSEIF rxLast - frm + 1 >= need THEN
                        IF Crc16Rx(frm + 1, need - 3) = rx{frm + need - 2} + 256 * rx{frm + need - 1} RETURN TRUE;
                        need := 0;
                    ENDIF
                ENDIF
                IF need > 0 THEN
                    IF ReadMore(FrameWait()) = -1 THEN
                        IF ClkRead(clkFrame) >= FRAME_S need := 0;
                    ELSEIF frm = 0 THEN
                        ! the peer was replaced: rx was emptied
                        RETURN FALSE;
                    ENDIF
                ENDIF
                IF need = 0 THEN
                    ! not a frame: its sync is dropped, the scan resumes at the byte after it
                    rxFirst := frm + 1;
                    frm := 0;
                ENDIF
            ELSE
                IF ReadMore(WaitTime()) < 0 RETURN FALSE;
            ENDIF
        ENDWHILE
        RETURN FALSE;
    ENDFUNC

    LOCAL PROC ServeOneFrame()
        ! serves the next frame (NextFrame: scanning, resynchronising, the frame time and the watchdog). A frame is
        ! consumed before it is handled (a reply that finds the peer gone starts a new session with rx empty). A
        ! silent peer (a PC that crashed without closing) gives way to a new one waiting.
        CheckRestart;
        IF NOT NextFrame() THEN
            Watchdog;
            IF ClkRead(clkHeard) >= SILENCE_S THEN
                IF IRB120ChanNewPeer() Reconnect;
            ENDIF
            RETURN;
        ENDIF
        rxFirst := frm + rx{frm + 1} + 6;
        ! a reply (type bit 0x80: a line echoing our own frames) is never a command: dropped, no reply
        IF rx{frm + 2} < T_REPLY THEN
            RestartClock clkValid;
            HandleFrame;
        ENDIF
        frm := 0;
    ENDPROC

    LOCAL PROC Watchdog()
        ! while the robot is commanded to move, the PC must send a valid frame (a STATE request will do) at least
        ! every HEARTBEAT_S; if it does not, the robot stops at once and holds, and the next motion command is
        ! refused
        IF status = S_MOVING THEN
            IF Arrived() THEN
                status := S_IDLE;
            ELSEIF ClkRead(clkValid) >= HEARTBEAT_S THEN
                HoldRobot\Quick;
                watchdogFired := TRUE;
                ErrWrite\W, "IRB120Server: watchdog stop", "no valid frame within HEARTBEAT_S while moving: held";
            ENDIF
        ENDIF
    ENDPROC

    LOCAL FUNC bool Arrived()
        ! the last motion is done: every axis within ARRIVED_DEG of its target (nothing left for a watchdog to stop)
        VAR jointtarget now;
        now := CJointT();
        RETURN Abs(now.robax.rax_1 - lastJoints.robax.rax_1) < ARRIVED_DEG AND Abs(now.robax.rax_2 - lastJoints.robax.rax_2) <
            ARRIVED_DEG AND Abs(now.robax.rax_3 - lastJoints.robax.rax_3) < ARRIVED_DEG AND Abs(now.robax.rax_4 -
            lastJoints.robax.rax_4) < ARRIVED_DEG AND Abs(now.robax.rax_5 - lastJoints.robax.rax_5) < ARRIVED_DEG AND
            Abs(now.robax.rax_6 - lastJoints.robax.rax_6) < ARRIVED_DEG;
    ENDFUNC

    ! ---------------------------------------------------------------- commands
    LOCAL PROC HandleFrame()
        VAR num kind;
        VAR num seq;
        VAR num crc;
        kind := rx{frm + 2};
        seq := rx{frm + 3};
        crc := rx{frm + rx{frm + 1} + 4} + 256 * rx{frm + rx{frm + 1} + 5};
        CheckRestart;
        IF seq = lastSeq AND kind = lastKind AND crc = lastCrc AND kind <> T_HELLO THEN
            ! a repeated frame (same number, type and CRC): answer again from the cache, never execute again. A HELLO
            ! is never answered from the cache: it is checked, and opens a session only if accepted
            SendTx;
            RETURN;
        ENDIF
        refusal := CheckFrame(kind, rx{frm + 1});
        IF refusal = E_OK THEN
            TEST kind
            CASE T_TOOL_STEP:
                ToolStep;
            CASE T_JOINTS:
                JointMove;
            CASE T_GRIPPER:
                SetGripper rx{frm + 4};
            CASE T_STOP:
                HoldRobot;
            CASE T_HELLO:
                ! only an accepted HELLO opens a session (lifts a restart hold): a refused one changes nothing
                IF rx{frm + 4} = PROTOCOL_VERSION THEN
                    StartSession;
                ELSE
                    refusal := E_VERSION;
                ENDIF
            CASE T_RESET:
                ResetMove;
            ENDTEST
        ENDIF
        IF refusal = E_OK THEN
            ! a refusal is logged again once a command other than a STATE (the heartbeat) has been accepted
            IF kind <> T_STATE lastLogged := E_OK;
        ELSEIF refusal <> lastLogged THEN
            ! each new kind of refusal is logged once: a PC repeating a refused step, with STATE requests between
            ! the tries, does not flood the log
            ErrWrite\I, "IRB120Server: refused", "command type " + NumToStr(kind, 0) + ", error " + NumToStr(refusal, 0);
            lastLogged := refusal;
        ENDIF
        lastSeq := seq;
        lastKind := kind;
        lastCrc := crc;
        BuildReply kind, seq;
        SendTx;
    ENDPROC

    LOCAL FUNC num CheckFrame(num kind, num len)
        VAR num want := -1;
        TEST kind
        CASE T_STATE, T_STOP:
            want := 0;
        CASE T_TOOL_STEP:
            want := 9;
        CASE T_JOINTS, T_RESET:
            want := 13;
        CASE T_GRIPPER, T_HELLO:
            want := 1;
        DEFAULT:
            RETURN E_UNKNOWN_TYPE;
        ENDTEST
        IF len <> want RETURN E_BAD_LENGTH;
        ! a gripper byte the protocol does not define (steps: 0 close, 1 open, 2 keep; GRIPPER: 0 or 1) is refused,
        ! as the PC's parser refuses it: never read as "close"
        TEST kind
        CASE T_TOOL_STEP:
            IF rx{frm + 12} > 2 RETURN E_BAD_VALUE;
        CASE T_JOINTS, T_RESET:
            IF rx{frm + 16} > 2 RETURN E_BAD_VALUE;
        CASE T_GRIPPER:
            IF rx{frm + 4} > 1 RETURN E_BAD_VALUE;
        ENDTEST
        ! a fault lasts as long as its cause: every frame reports it, motion commands are refused
        IF DOutput(doEstop) = 1 OR DOutput(doMotors) = 0 THEN
            status := S_FAULT;
        ELSEIF status = S_FAULT THEN
            status := S_IDLE;
        ENDIF
        IF kind = T_STATE OR kind = T_STOP OR kind = T_HELLO RETURN E_OK;
        IF DOutput(doEstop) = 1 RETURN E_ESTOP;
        IF DOutput(doMotors) = 0 RETURN E_MOTORS_OFF;
        ! read before every motion command: the key switch can turn at any time
        IF NOT ALLOW_AUTO AND OpMode() <> OP_MAN_PROG RETURN E_OPERATING_MODE;
        IF watchdogFired THEN
            ! the PC must learn that the robot was stopped: this command is refused, the next one runs
            watchdogFired := FALSE;
            RETURN E_WATCHDOG;
        ENDIF
        ! after a restart, motion waits for a new session: frames the PC sent before the stop (still buffered) and
        ! a PC that did not notice the stop are refused until it sends a HELLO the server accepts
        IF restartHeld RETURN E_RESTARTED;
        RETURN E_OK;
    ENDFUNC

    LOCAL PROC ToolStep()
        VAR num dx;
        VAR num dy;
        VAR num dz;
        VAR num rot;
        VAR robtarget here;
        VAR robtarget target;
        VAR jointtarget jNow;
        VAR jointtarget jTarget;
        VAR num grip;
        dx := Int16At(4) / 100;
        dy := Int16At(6) / 100;
        dz := Int16At(8) / 100;
        rot := Int16At(10) / 1000;
        IF Abs(dx) > STEP_POS_MM OR Abs(dy) > STEP_POS_MM OR Abs(dz) > STEP_POS_MM OR Abs(rot) > STEP_ROT_DEG THEN
            refusal := E_STEP_LIMIT;
            RETURN;
        ENDIF
        grip := GripperChange(rx{frm + 12});
        IF dx = 0 AND dy = 0 AND dz = 0 AND rot = 0 THEN
            ! a zero-length step moves nothing: answered without queuing a motion. Its gripper change waits until the
            ! robot stands in position: SetDO fires when the program pointer passes it, which with a step still
            ! under way would be that step early (a grasp closing before the fingers are round the object)
            IF grip >= 0 THEN
                WaitRob\InPos;
                SetGripper grip;
            ENDIF
            RETURN;
        ENDIF
        here := CRobT(\Tool:=tGripper\WObj:=wobj0);
        ! translate in the tool frame, then rotate about the approach axis (tool x): pd_ee_delta_tool
        target := RelTool(here, dx, dy, dz\Rx:=rot);
        IF NOT InsideBox(target.trans) THEN
            refusal := E_WORKSPACE;
            RETURN;
        ENDIF
        jNow := CJointT();
        jTarget := CalcJointT(target, tGripper\WObj:=wobj0);
        IF refusal <> E_OK RETURN;
        refusal := CheckJoints(jNow, jTarget);
        IF refusal <> E_OK RETURN;
        IF grip < 0 THEN
            MoveL target, vStep, zStep, tGripper\WObj:=wobj0;
        ELSE
            ! the gripper changes where the robot reaches the target (the middle of its corner path; at a stop point,
            ! there), tied to the path: SetDO after the MoveL would fire when the program pointer passes it, a step
            ! early while the step before is still under way
            MoveLDO target, vStep, zStep, tGripper\WObj:=wobj0, doGripper, grip;
            gripCmd := grip;
        ENDIF
        lastTarget := target;
        lastJoints := jTarget;
        status := S_MOVING;
    ERROR
        IF ERRNO = ERR_ROBLIMIT THEN
            refusal := E_JOINT_LIMIT;
            TRYNEXT;
        ELSEIF ERRNO = ERR_OUTSIDE_REACH THEN
            refusal := E_UNREACHABLE;
            TRYNEXT;
        ENDIF
        RAISE;
    ENDPROC

    LOCAL PROC JointMove()
        VAR jointtarget jNow;
        VAR jointtarget jTarget;
        VAR robtarget tcp;
        VAR num grip;
        jNow := CJointT();
        jTarget := jNow;
        jTarget.robax.rax_1 := Int16At(4) * 0.02;
        jTarget.robax.rax_2 := Int16At(6) * 0.02;
        jTarget.robax.rax_3 := Int16At(8) * 0.02;
        jTarget.robax.rax_4 := Int16At(10) * 0.02;
        jTarget.robax.rax_5 := Int16At(12) * 0.02;
        jTarget.robax.rax_6 := Int16At(14) * 0.02;
        refusal := CheckJoints(jNow, jTarget);
        IF refusal <> E_OK RETURN;
        tcp := CalcRobT(jTarget, tGripper\WObj:=wobj0);
        IF NOT InsideBox(tcp.trans) THEN
            refusal := E_WORKSPACE;
            RETURN;
        ENDIF
        grip := GripperChange(rx{frm + 16});
        IF grip < 0 THEN
            MoveAbsJ jTarget, vStep, zStep, tGripper\WObj:=wobj0;
        ELSE
            ! MoveAbsJ has no DO form (MoveLDO, MoveJDO take a robtarget): a step that changes the gripper ends at a
            ! stop point, and the output is set once the robot is there
            MoveAbsJ jTarget, vStep, fine, tGripper\WObj:=wobj0;
            SetGripper grip;
        ENDIF
        lastTarget := tcp;
        lastJoints := jTarget;
        status := S_MOVING;
    ENDPROC

    LOCAL PROC ResetMove()
        ! one joint move to the episode's start pose at vReset, ending at a stop point: the target inside the joint
        ! limits and the TCP inside the workspace box at RESET_CHECKS points along the joint path. Answered once the
        ! robot is there (the PC waits as long as the move takes).
        VAR jointtarget jNow;
        VAR jointtarget jTarget;
        VAR jointtarget jMid;
        VAR robtarget tcp;
        VAR num now{6};
        VAR num goal{6};
        VAR num s;
        jNow := CJointT();
        goal := [Int16At(4) * 0.02, Int16At(6) * 0.02, Int16At(8) * 0.02, Int16At(10) * 0.02, Int16At(12) * 0.02,
            Int16At(14) * 0.02];
        now := [jNow.robax.rax_1, jNow.robax.rax_2, jNow.robax.rax_3, jNow.robax.rax_4, jNow.robax.rax_5, jNow.robax.rax_6];
        FOR i FROM 1 TO 6 DO
            IF goal{i} < JOINT_LOW{i} OR goal{i} > JOINT_HIGH{i} THEN
                refusal := E_JOINT_LIMIT;
                RETURN;
            ENDIF
        ENDFOR
        jMid := jNow;
        FOR k FROM 1 TO RESET_CHECKS DO
            s := k / RESET_CHECKS;
            jMid.robax.rax_1 := now{1} + s * (goal{1} - now{1});
            jMid.robax.rax_2 := now{2} + s * (goal{2} - now{2});
            jMid.robax.rax_3 := now{3} + s * (goal{3} - now{3});
            jMid.robax.rax_4 := now{4} + s * (goal{4} - now{4});
            jMid.robax.rax_5 := now{5} + s * (goal{5} - now{5});
            jMid.robax.rax_6 := now{6} + s * (goal{6} - now{6});
            tcp := CalcRobT(jMid, tGripper\WObj:=wobj0);
            IF NOT InsideBox(tcp.trans) THEN
                refusal := E_WORKSPACE;
                RETURN;
            ENDIF
        ENDFOR
        jTarget := jMid;
        IF rx{frm + 16} <> 2 SetGripper rx{frm + 16};
        MoveAbsJ jTarget, vReset, fine, tGripper\WObj:=wobj0;
        lastTarget := tcp;
        lastJoints := jTarget;
        status := S_IDLE;
    ENDPROC

    LOCAL FUNC num CheckJoints(jointtarget jNow, jointtarget jTarget)
        VAR num now{6};
        VAR num target{6};
        now := [jNow.robax.rax_1, jNow.robax.rax_2, jNow.robax.rax_3, jNow.robax.rax_4, jNow.robax.rax_5, jNow.robax.rax_6];
        target := [jTarget.robax.rax_1, jTarget.robax.rax_2, jTarget.robax.rax_3, jTarget.robax.rax_4, jTarget.robax.rax_5,
            jTarget.robax.rax_6];
        FOR i FROM 1 TO 6 DO
            IF target{i} < JOINT_LOW{i} OR target{i} > JOINT_HIGH{i} RETURN E_JOINT_LIMIT;
            IF Abs(target{i} - now{i}) > JOINT_STEP_DEG{i} RETURN E_JOINT_SPEED;
        ENDFOR
        RETURN E_OK;
    ENDFUNC

    LOCAL FUNC bool InsideBox(pos p)
        RETURN p.x >= WORKSPACE_LOW.x AND p.x <= WORKSPACE_HIGH.x AND p.y >= WORKSPACE_LOW.y AND p.y <= WORKSPACE_HIGH.y
            AND p.z >= WORKSPACE_LOW.z AND p.z <= WORKSPACE_HIGH.z;
    ENDFUNC

    LOCAL PROC SetGripper(num value)
        ! the gripper output now (value 1 open, 0 closed), when the program pointer passes
        SetDO doGripper, value;
        gripCmd := value;
    ENDPROC

    LOCAL FUNC num GripperChange(num wanted)
        ! the output value a command's gripper byte (0 close, 1 open, 2 keep: CheckFrame refused any other) changes
        ! to, or -1 when it changes nothing (2, or the value the output already has or is set to along the queued path)
        IF wanted = 2 OR wanted = gripCmd RETURN -1;
        RETURN wanted;
    ENDFUNC

    ! ---------------------------------------------------------------- replying
    LOCAL PROC BuildReply(num kind, num seq)
        ! tx: sync, length 26, type 0x80 + kind, seq, state payload, CRC
        VAR jointtarget j;
        VAR robtarget p;
        VAR num q{4};
        VAR num big := 1;
        VAR num sign := 1;
        VAR num k := 0;
        IF status = S_MOVING AND Arrived() status := S_IDLE;
        j := CJointT();
        p := lastTarget;
        q := [p.rot.q1, p.rot.q2, p.rot.q3, p.rot.q4];
        FOR i FROM 2 TO 4 DO
            IF Abs(q{i}) > Abs(q{big}) big := i;
        ENDFOR
        IF q{big} < 0 sign := -1;
        tx{1} := SYNC;
        tx{2} := 26;
        ! 0x80 + type, a byte for every type answered (replies, 0x80 and up, are dropped before)
        IF kind >= T_STATE AND kind <= T_RESET THEN
            tx{3} := T_REPLY + kind;
        ELSE
            tx{3} := T_REPLY + (kind MOD T_REPLY);
        ENDIF
        tx{4} := seq;
        tx{5} := status + 4 * (big - 1) + 128 * DOutput(doGripper);
        tx{6} := refusal;
        PutInt16 7, j.robax.rax_1 / 0.02;
        PutInt16 9, j.robax.rax_2 / 0.02;
        PutInt16 11, j.robax.rax_3 / 0.02;
        PutInt16 13, j.robax.rax_4 / 0.02;
        PutInt16 15, j.robax.rax_5 / 0.02;
        PutInt16 17, j.robax.rax_6 / 0.02;
        PutInt16 19, p.trans.x / 0.05;
        PutInt16 21, p.trans.y / 0.05;
        PutInt16 23, p.trans.z / 0.05;
        FOR i FROM 1 TO 4 DO
            IF i <> big THEN
                PutInt16 25 + 2 * k, sign * q{i} * 46339.5;
                k := k + 1;
            ENDIF
        ENDFOR
        PutCrcTx 26 + 3;
        txLen := 32;
    ENDPROC

    LOCAL PROC SendTx()
        IF NOT IRB120ChanWrite(tx, txLen) Reconnect;
    ENDPROC

    ! ---------------------------------------------------------------- bytes
    LOCAL FUNC num Int16At(num i)
        ! little-endian int16 at byte i of the frame (rx{frm + i}, rx{frm + i + 1}; 4: the first payload byte)
        VAR num v;
        v := rx{frm + i} + 256 * rx{frm + i + 1};
        IF v >= 32768 v := v - 65536;
        RETURN v;
    ENDFUNC

    LOCAL PROC PutInt16(num i, num value)
        VAR num v;
        v := Round(value);
        IF v > 32767 v := 32767;
        IF v < -32768 v := -32768;
        IF v < 0 v := v + 65536;
        tx{i} := v MOD 256;
        tx{i + 1} := v DIV 256;
    ENDPROC

    LOCAL FUNC num Crc16Rx(num first, num count)
        ! CRC-16/CCITT-FALSE of the count bytes from rx{first} (length, type, seq, payload)
        VAR byte hi := 255;
        VAR byte lo := 255;
        VAR num t;
        FOR i FROM first TO first + count - 1 DO
            t := BitXOr(hi, rx{i}) + 1;
            hi := BitXOr(lo, CRC_HI{t});
            lo := CRC_LO{t};
        ENDFOR
        RETURN 256 * hi + lo;
    ENDFUNC

    LOCAL PROC PutCrcTx(num count)
        ! CRC of tx{2..count + 1}, appended low byte first
        VAR byte hi := 255;
        VAR byte lo := 255;
        VAR num t;
        FOR i FROM 2 TO count + 1 DO
            t := BitXOr(hi, tx{i}) + 1;
            hi := BitXOr(lo, CRC_HI{t});
            lo := CRC_LO{t};
        ENDFOR
        tx{count + 2} := lo;
        tx{count + 3} := hi;
    ENDPROC
ENDMODULE
