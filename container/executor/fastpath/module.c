/* _fastpath: the executor's hot path in C: readiness, takes, the async chain.
 *
 * One module from one source per job (shared declarations in fastpath.h):
 * held.c, notifier.c, waitset.c, taker.c, service.c, lock.c, lanes.c,
 * express.c, watcher.c, handoff.c, meter.c, handles.c; this file makes the module and
 * holds its few free functions. Its pure-Python twin, the executable
 * specification of what it does, is container/executor/_pyengine/.
 *
 * Notifier: event-driven readiness for rcl subscriptions, clients and services.
 *
 * Why: a wait set is level-triggered and rebuilt (attached, detached) on
 * every rcl_wait, and a message published by one node of this process to
 * another is only found by the next wait. rmw offers a per-entity "new data"
 * callback instead, which Fast DDS calls in the publishing thread for a
 * reader of the same process, or in its receive thread for a remote writer.
 * This module registers that callback, records which entities became ready,
 * and triggers one rcl guard condition only while the executor's thread is
 * actually asleep in rcl_wait (armed). The executor then takes what is
 * ready without another wait: a ping-pong between two nodes of one process
 * never enters rcl_wait at all. Nor is it triggered when a lane's worker
 * publishes to a plain callback it will carry on to itself, while the
 * waiter wakes within DEFER_MAX_NS anyway (see on_event).
 *
 * Entities are given as their rclpy handles, which the notifier holds and
 * enters from ``watch`` until ``unwatch`` (held.c); they are reported by
 * their rcl address (``handle.pointer``), a key. After ``unwatch`` returns
 * no callback runs for the entity any more (rmw serialises setting and
 * calling the callback), and only then is the handle let go.
 *
 * WaitSet: an rcl wait set over entities given once (their handles held),
 * filled, waited on and read in one call: rclpy's wait set takes a call per
 * entity to fill and one per kind to read, on every wait.
 *
 * Taker: rcl_take of one subscription into a C message kept across takes,
 * converted with the message type's own rosidl capsules; what rclpy's
 * take_message does, without rebuilding the message, the pybind11 call
 * and the message-info dictionary nobody asked for.
 *
 * Server and Caller (service.c): the same for a service's requests and a
 * client's responses, and a service's answers sent: rclpy's three calls of
 * a round trip (its take_request, send_response and take_response) took
 * 16 us here, these 8-10 us (the conversions are the types' own).
 *
 * Slots, Work, Token, Runner, KeepLast, Route, Routes (lanes.c): a callback
 * group's admission state and the objects both languages read, so that the
 * Python lanes and the async chain follow one admission protocol and
 * neither depends on the other's attribute names.
 *
 * Meter (meter.c): what one entity's callbacks cost, timed where each step
 * runs, whichever path runs it.
 *
 * HandleMeter (handles.c): the event loop's call_soon, which schedules a
 * node's handles metered as its own (the loop's hottest method, in C).
 *
 * Express: the loop thread's chain of async def subscription callbacks
 * (take, admit to the callback group's lane, first step, release) without
 * returning to Python between messages, and the same for async def timer
 * callbacks after a wait; see express.c.
 */
#include "fastpath.h"

static PyObject * mark_carrier(PyObject * Py_UNUSED(module), PyObject * Py_UNUSED(ignored))
{
  carrier_thread = 1;
  atomic_store(&carriers_exist, 1);
  Py_RETURN_NONE;
}

/* publisher_gid(publisher): the gid of the rcl publisher of that rclpy
 * handle (held and entered for the call), as rclpy 9's message info gives
 * a message's publisher_gid. */
static PyObject * publisher_gid(PyObject * Py_UNUSED(module), PyObject * handle)
{
  Held publisher;
  rmw_publisher_t * rmw_publisher;
  rmw_gid_t gid;
  rmw_ret_t ret;
  if (held_enter(&publisher, handle) < 0) {
    return NULL;
  }
  rmw_publisher = rcl_publisher_get_rmw_handle((const rcl_publisher_t *)publisher.pointer);
  if (rmw_publisher == NULL) {
    held_exit(&publisher);
    return rcl_failed("rcl_publisher_get_rmw_handle");
  }
  ret = rmw_get_gid_for_publisher(rmw_publisher, &gid);
  held_exit(&publisher);
  if (ret != RMW_RET_OK) {
    PyErr_Format(PyExc_RuntimeError, "rmw_get_gid_for_publisher failed: %s", rmw_get_error_string().str);
    rmw_reset_error();
    return NULL;
  }
  return gid_dict(&gid);
}

/* poll(wait_set, timeout_ns) -> None: rcl_wait on rclpy's wait set (its
 * handle, held and entered for the call) keeping the GIL, where rclpy's own
 * ``wait`` would let go of it even for a poll: WaitSet_wait's poll, for the
 * wait set rclpy fills. */
static PyObject * poll_wait_set(PyObject * Py_UNUSED(module), PyObject * const * args, Py_ssize_t nargs)
{
  Held wait_set;
  long long timeout;
  rcl_ret_t ret;
  if (nargs != 2) {
    PyErr_SetString(PyExc_TypeError, "poll(wait_set, timeout_ns)");
    return NULL;
  }
  timeout = PyLong_AsLongLong(args[1]);
  if ((timeout == -1 && PyErr_Occurred()) || held_enter(&wait_set, args[0]) < 0) {
    return NULL;
  }
  ret = rcl_wait((rcl_wait_set_t *)wait_set.pointer, (int64_t)poll_timeout(timeout));
  held_exit(&wait_set);
  if (ret != RCL_RET_OK && ret != RCL_RET_TIMEOUT) {
    return rcl_failed("rcl_wait");
  }
  Py_RETURN_NONE;
}

static PyMethodDef module_methods[] = {
  {"poll", (PyCFunction)(void (*)(void))poll_wait_set, METH_FASTCALL,
   "poll(wait_set, timeout_ns) -> None: rcl_wait on rclpy's wait set (its handle), keeping the GIL "
   "(for a wait whose guard condition is already triggered)"},
  {"publisher_gid", publisher_gid, METH_O,
   "publisher_gid(publisher) -> dict: the gid of the rcl publisher of that rclpy handle, as rclpy 9's message "
   "info gives it ({'implementation_identifier': str, 'data': bytes})"},
  {"mark_carrier", mark_carrier, METH_NOARGS,
   "mark_carrier() -> None: this thread takes, after each plain callback, what it published to other "
   "plain callbacks (Notifier.carry); a notifier's waiter that wakes soon anyway is not woken for that"},
  {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
  PyModuleDef_HEAD_INIT,
  .m_name = "_fastpath",
  .m_doc = "The executor's hot path: readiness and takes of rcl entities (see the C source for why).",
  .m_size = -1,
  .m_methods = module_methods,
};

PyMODINIT_FUNC PyInit__fastpath(void)
{
  static struct {
    const char * name;
    PyTypeObject * type;
  } types[] = {
    {"Notifier", &NotifierType}, {"Lock", &LockType}, {"Taker", &TakerType}, {"WaitSet", &WaitSetType},
    {"Express", &ExpressType}, {"Token", &TokenType}, {"Work", &WorkType}, {"Runner", &RunnerType},
    {"KeepLast", &KeepLastType}, {"Slots", &SlotsType}, {"Route", &RouteType}, {"Routes", &RoutesType},
    {"FdWatcher", &FdWatcherType}, {"Handoff", &HandoffType}, {"Meter", &MeterType},
    {"Server", &ServerType}, {"Caller", &CallerType}, {"HandleMeter", &HandleMeterType},
    {"Deadline", &DeadlineType},
  };
  size_t i;
  PyObject * m;
  if (handle_meter_ready() < 0) {
    return NULL;
  }
  for (i = 0; i < sizeof(types) / sizeof(types[0]); ++i) {
    if (PyType_Ready(types[i].type) < 0) {
      return NULL;
    }
  }
  m = PyModule_Create(&module);
  if (m == NULL) {
    return NULL;
  }
  for (i = 0; i < sizeof(types) / sizeof(types[0]); ++i) {
    Py_INCREF(types[i].type);
    if (PyModule_AddObject(m, types[i].name, (PyObject *)types[i].type) < 0) {
      Py_DECREF(types[i].type);
      Py_DECREF(m);
      return NULL;
    }
  }
  if (PyModule_AddFunctions(m, express_functions) < 0 || PyModule_AddFunctions(m, meter_functions) < 0 ||
      PyModule_AddIntConstant(m, "SUBSCRIPTION", KIND_SUBSCRIPTION) < 0 ||
      PyModule_AddIntConstant(m, "CLIENT", KIND_CLIENT) < 0 ||
      PyModule_AddIntConstant(m, "SERVICE", KIND_SERVICE) < 0 ||
      PyModule_AddIntConstant(m, "EVENT", KIND_EVENT) < 0 ||
      PyModule_AddIntConstant(m, "DRAIN", (long)DRAIN) < 0) {
    Py_DECREF(m);
    return NULL;
  }
  return m;
}
