"""The A2L's description of the XCP slave itself: the module's ``IF_DATA XCP`` block (the protocol layer,
the DAQ processor with its events and predefined lists, the page processor, the UDP address), the
calibration segment's (its two pages and who may write them), and the A2ML those blocks are written in.

The A2ML declares the part of ASAM's XCP 1.x ``IF_DATA`` layout this slave uses, each field in the
standard's order, so a tool that reads the standard's definition reads the same values; ``a2ltool
--ifdata-cleanup`` keeps only blocks that parse by it (the tests check that both survive).
"""

from __future__ import annotations

import ipaddress

from cantools.database import Database

from estimator.service.xcp import protocol as p
from estimator.service.xcp.daq_lists import EVENTS, MAX_DYNAMIC_LISTS, MAX_ENTRY_BYTES, predefined_lists

A2ML = """    /begin A2ML
      struct Protocol_Layer {
        uint;  /* XCP protocol layer version */
        uint;  /* T1 [ms] */
        uint;  /* T2 [ms] */
        uint;  /* T3 [ms] */
        uint;  /* T4 [ms] */
        uint;  /* T5 [ms] */
        uint;  /* T6 [ms] */
        uint;  /* T7 [ms] */
        uchar;  /* MAX_CTO */
        uint;  /* MAX_DTO */
        enum { "BYTE_ORDER_MSB_LAST" = 0, "BYTE_ORDER_MSB_FIRST" = 1 };
        enum { "ADDRESS_GRANULARITY_BYTE" = 1, "ADDRESS_GRANULARITY_WORD" = 2, "ADDRESS_GRANULARITY_DWORD" = 4 };
        taggedstruct {
          ("OPTIONAL_CMD" enum {
%(commands)s
          })*;
        };
      };
      struct Daq {
        enum { "STATIC" = 0, "DYNAMIC" = 1 };
        uint;  /* MAX_DAQ */
        uint;  /* MAX_EVENT_CHANNEL */
        uchar;  /* MIN_DAQ */
        enum { "OPTIMISATION_TYPE_DEFAULT" = 0 };
        enum { "ADDRESS_EXTENSION_FREE" = 0, "ADDRESS_EXTENSION_ODT" = 1, "ADDRESS_EXTENSION_DAQ" = 3 };
        enum { "IDENTIFICATION_FIELD_TYPE_ABSOLUTE" = 0, "IDENTIFICATION_FIELD_TYPE_RELATIVE_BYTE" = 1,
               "IDENTIFICATION_FIELD_TYPE_RELATIVE_WORD" = 2, "IDENTIFICATION_FIELD_TYPE_RELATIVE_WORD_ALIGNED" = 3 };
        enum { "GRANULARITY_ODT_ENTRY_SIZE_DAQ_BYTE" = 1, "GRANULARITY_ODT_ENTRY_SIZE_DAQ_WORD" = 2,
               "GRANULARITY_ODT_ENTRY_SIZE_DAQ_DWORD" = 4, "GRANULARITY_ODT_ENTRY_SIZE_DAQ_DLONG" = 8 };
        uchar;  /* MAX_ODT_ENTRY_SIZE_DAQ */
        enum { "NO_OVERLOAD_INDICATION" = 0, "OVERLOAD_INDICATION_PID" = 1, "OVERLOAD_INDICATION_EVENT" = 2 };
        taggedstruct {
          "PRESCALER_SUPPORTED";
          block "TIMESTAMP_SUPPORTED" struct {
            uint;  /* TIMESTAMP_TICKS */
            enum { "NO_TIME_STAMP" = 0, "SIZE_BYTE" = 1, "SIZE_WORD" = 2, "SIZE_DWORD" = 4 };
            enum { "UNIT_1NS" = 0, "UNIT_10NS" = 1, "UNIT_100NS" = 2, "UNIT_1US" = 3, "UNIT_10US" = 4,
                   "UNIT_100US" = 5, "UNIT_1MS" = 6, "UNIT_10MS" = 7, "UNIT_100MS" = 8, "UNIT_1S" = 9 };
            taggedstruct { "TIMESTAMP_FIXED"; };
          };
          (block "DAQ_LIST" struct {
            uint;  /* DAQ_LIST_NUMBER */
            taggedstruct {
              "DAQ_LIST_TYPE" enum { "DAQ" = 1, "STIM" = 2, "DAQ_STIM" = 3 };
              "MAX_ODT" uchar;
              "MAX_ODT_ENTRIES" uchar;
              "FIRST_PID" uchar;
              "EVENT_FIXED" uint;
              block "PREDEFINED" taggedstruct {
                (block "ODT" struct {
                  uchar;  /* ODT number */
                  taggedstruct {
                    ("ODT_ENTRY" struct {
                      uchar;  /* ODT_ENTRY number */
                      ulong;  /* address of the element */
                      uchar;  /* address extension of the element */
                      uchar;  /* size of the element [AG] */
                      uchar;  /* BIT_OFFSET */
                    })*;
                  };
                })*;
              };
            };
          })*;
          (block "EVENT" struct {
            char[101];  /* EVENT_CHANNEL_NAME */
            char[9];  /* EVENT_CHANNEL_SHORT_NAME */
            uint;  /* EVENT_CHANNEL_NUMBER */
            enum { "DAQ" = 1, "STIM" = 2, "DAQ_STIM" = 3 };
            uchar;  /* MAX_DAQ_LIST */
            uchar;  /* TIME_CYCLE */
            uchar;  /* TIME_UNIT */
            uchar;  /* PRIORITY */
          })*;
        };
      };
      struct Pag {
        uchar;  /* MAX_SEGMENTS */
        taggedstruct { "FREEZE_SUPPORTED"; };
      };
      struct Segment {
        uchar;  /* segment logical number */
        uchar;  /* number of pages */
        uchar;  /* address extension */
        uchar;  /* compression method */
        uchar;  /* encryption method */
        taggedstruct {
          (block "PAGE" struct {
            uchar;  /* page number */
            enum { "ECU_ACCESS_NOT_ALLOWED" = 0, "ECU_ACCESS_WITHOUT_XCP_ONLY" = 1, "ECU_ACCESS_WITH_XCP_ONLY" = 2,
                   "ECU_ACCESS_DONT_CARE" = 3 };
            enum { "XCP_READ_ACCESS_NOT_ALLOWED" = 0, "XCP_READ_ACCESS_WITHOUT_ECU_ONLY" = 1,
                   "XCP_READ_ACCESS_WITH_ECU_ONLY" = 2, "XCP_READ_ACCESS_DONT_CARE" = 3 };
            enum { "XCP_WRITE_ACCESS_NOT_ALLOWED" = 0, "XCP_WRITE_ACCESS_WITHOUT_ECU_ONLY" = 1,
                   "XCP_WRITE_ACCESS_WITH_ECU_ONLY" = 2, "XCP_WRITE_ACCESS_DONT_CARE" = 3 };
          })*;
        };
      };
      taggedstruct Common_Parameters {
        block "PROTOCOL_LAYER" struct Protocol_Layer;
        block "SEGMENT" struct Segment;
        block "DAQ" struct Daq;
        block "PAG" struct Pag;
      };
      struct UDP_IP_Parameters {
        uint;  /* XCP on UDP_IP version */
        uint;  /* PORT */
        taggedunion {
          "HOST_NAME" char[256];
          "ADDRESS" char[15];
        };
      };
      block "IF_DATA" taggedunion if_data {
        "XCP" struct {
          taggedstruct Common_Parameters;
          taggedstruct {
            block "XCP_ON_UDP_IP" struct {
              struct UDP_IP_Parameters;
              taggedstruct Common_Parameters;
            };
          };
        };
      };
    /end A2ML"""


def a2ml() -> str:
    """The A2ML block (its OPTIONAL_CMD codes from :data:`~estimator.service.xcp.protocol.OPTIONAL_COMMANDS`)."""
    commands = ",\n".join(f'            "{name}" = 0x{getattr(p, name):02X}' for name in p.OPTIONAL_COMMANDS)
    return A2ML % {"commands": commands}


def _address(host: str) -> str:
    """The UDP address as the A2L gives it: ``ADDRESS`` for an IPv4 address, else ``HOST_NAME``."""
    try:
        ipaddress.IPv4Address(host)
        return f'ADDRESS "{host}"'
    except ValueError:
        return f'HOST_NAME "{host}"'


def if_data(db: Database, address: tuple[str, int]) -> list[str]:
    """The MODULE's ``IF_DATA XCP`` lines for the slave of the DBC ``db`` listening on ``address``."""
    lists = predefined_lists(db)
    out = ["    /begin IF_DATA XCP",
           "      /begin PROTOCOL_LAYER",
           f"        0x{p.PROTOCOL_LAYER_VERSION << 8:04X} {' '.join(str(t) for t in p.TIMEOUTS_MS)} {p.MAX_CTO} {p.MAX_DTO}",
           "        BYTE_ORDER_MSB_LAST ADDRESS_GRANULARITY_BYTE",
           *(f"        OPTIONAL_CMD {name}" for name in p.OPTIONAL_COMMANDS),
           "      /end PROTOCOL_LAYER",
           "      /begin DAQ",
           f"        DYNAMIC {len(lists) + MAX_DYNAMIC_LISTS} {len(EVENTS)} {len(lists)}",
           "        OPTIMISATION_TYPE_DEFAULT ADDRESS_EXTENSION_FREE IDENTIFICATION_FIELD_TYPE_ABSOLUTE",
           f"        GRANULARITY_ODT_ENTRY_SIZE_DAQ_BYTE {MAX_ENTRY_BYTES} NO_OVERLOAD_INDICATION",
           "        PRESCALER_SUPPORTED",
           "        /begin TIMESTAMP_SUPPORTED 1 SIZE_DWORD UNIT_1US TIMESTAMP_FIXED /end TIMESTAMP_SUPPORTED"]
    for number, pl in enumerate(lists):     # one ODT a list: its PID is its number
        out += [f"        /begin DAQ_LIST {number}",
                f"          DAQ_LIST_TYPE DAQ MAX_ODT 1 MAX_ODT_ENTRIES {len(pl.entries)} FIRST_PID {number}"
                f" EVENT_FIXED {pl.event}",
                "          /begin PREDEFINED", "            /begin ODT 0",
                *(f"              ODT_ENTRY {k} 0x{a:X} 0 {size} 0xFF" for k, (a, size) in enumerate(pl.entries)),
                "            /end ODT", "          /end PREDEFINED",
                "        /end DAQ_LIST"]
    for channel, e in enumerate(EVENTS):
        out.append(f'        /begin EVENT "{e.name}" "{e.short}" {channel} DAQ 0xFF {e.cycle} {e.unit} 0 /end EVENT')
    out += ["      /end DAQ",
            "      /begin PAG 1 /end PAG",
            "      /begin XCP_ON_UDP_IP",
            f"        0x{p.TRANSPORT_LAYER_VERSION << 8:04X} {address[1]} {_address(address[0])}",
            "      /end XCP_ON_UDP_IP",
            "    /end IF_DATA"]
    return out


def segment(writes: bool) -> list[str]:
    """The calibration MEMORY_SEGMENT's ``IF_DATA XCP``: segment 0 of two pages, both used by the
    estimator and read by XCP at any time; page 0 (working) written by XCP when ``writes``, page 1
    (reference) never."""
    working = "XCP_WRITE_ACCESS_DONT_CARE" if writes else "XCP_WRITE_ACCESS_NOT_ALLOWED"
    return ["        /begin IF_DATA XCP",
            "          /begin SEGMENT 0 2 0 0 0",
            *(f"            /begin PAGE {page} ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE {access} /end PAGE"
              for page, access in ((0, working), (1, "XCP_WRITE_ACCESS_NOT_ALLOWED"))),
            "          /end SEGMENT",
            "        /end IF_DATA"]


__all__ = ["a2ml", "if_data", "segment"]
