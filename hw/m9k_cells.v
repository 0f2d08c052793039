// Port directions of the M9K cell that `memory_libmap` makes from hw/m9k.lib. Only its
// count matters, so it stays a blackbox; without this declaration its pins have no
// direction, and abc9 removes the logic that only feeds or reads them.
(* blackbox *)
module maglog_m9k_sdp (PORT_R_CLK, PORT_R_CLK_EN, PORT_R_ADDR, PORT_R_RD_DATA,
                  PORT_W_CLK, PORT_W_CLK_EN, PORT_W_ADDR, PORT_W_WR_DATA,
                  PORT_W_WR_EN, PORT_W_WR_BE);
    parameter INIT = 0;
    parameter PORT_R_WIDTH = 36;
    parameter PORT_W_WIDTH = 36;
    parameter PORT_W_WR_BE_WIDTH = 4;
    input PORT_R_CLK;
    input PORT_R_CLK_EN;
    input [12:0] PORT_R_ADDR;
    output [PORT_R_WIDTH-1:0] PORT_R_RD_DATA;
    input PORT_W_CLK;
    input PORT_W_CLK_EN;
    input [12:0] PORT_W_ADDR;
    input [PORT_W_WIDTH-1:0] PORT_W_WR_DATA;
    input PORT_W_WR_EN;
    input [PORT_W_WR_BE_WIDTH-1:0] PORT_W_WR_BE;
endmodule
