/* HandleMeter: the event loop's call_soon, which meters what a node's code schedules.
 *
 * The executor's own loop (container/executor/_loop.py) credits each handle
 * to the node whose code scheduled it: the node is in the context the
 * handle is scheduled in (a ContextVar, see _owners.py), and its callback
 * is scheduled wrapped in that node's Meter.call. asyncio schedules every
 * wake-up of every task through the loop's call_soon: that is the loop's
 * hottest method, and a Python override of it cost about 1 us a call on
 * this project's VM (a byte bounced between two nodes' asyncio streams, 6%
 * of a round trip's CPU). This is that override, in C: a loop class takes
 * it as its first base, the loop's own call_soon second.
 *
 * A call goes through unchanged when the context names the executor's own
 * work, or when the callback is a step or a wake-up of an asyncio task (its
 * __self__ is a Task: each step of a node's task is metered by the task
 * factory, and a lane's runner task carries callbacks metered already).
 * Otherwise it is scheduled as account.call(arrived, callback, *args),
 * where account = owner.account("loop_callback") and owner is the node's
 * (the unattributed owner when the context names nobody, or is not a
 * contextvars.Context), and arrived is now: its lateness is its wait for
 * the loop. */
#include "fastpath.h"

typedef struct {
  PyObject_HEAD
  PyObject * owner;        /* the ContextVar naming whose code runs */
  PyObject * executor;     /* its value in the executor's own work */
  PyObject * task_type;    /* asyncio.Task */
  PyObject * call_soon;    /* the loop's own call_soon, unbound */
  PyObject * unattributed; /* the owner of work nobody's context names */
} HandleMeterObject;

/* HandleMeter(owner, executor, task_type, call_soon, unattributed) */
static int HandleMeter_init(HandleMeterObject * self, PyObject * args, PyObject * kwargs)
{
  PyObject * owner, * executor, * task_type, * call_soon, * unattributed;
  if (kwargs != NULL && PyDict_GET_SIZE(kwargs) > 0) {
    PyErr_SetString(PyExc_TypeError, "HandleMeter(owner, executor, task_type, call_soon, unattributed)");
    return -1;
  }
  if (!PyArg_ParseTuple(args, "OOOOO:HandleMeter", &owner, &executor, &task_type, &call_soon, &unattributed)) {
    return -1;
  }
  if (!PyContextVar_CheckExact(owner) || !PyType_Check(task_type) || !PyCallable_Check(call_soon)) {
    PyErr_SetString(
      PyExc_TypeError, "HandleMeter(owner: ContextVar, executor, task_type: type, call_soon: callable, unattributed)");
    return -1;
  }
  Py_XSETREF(self->owner, Py_NewRef(owner));
  Py_XSETREF(self->executor, Py_NewRef(executor));
  Py_XSETREF(self->task_type, Py_NewRef(task_type));
  Py_XSETREF(self->call_soon, Py_NewRef(call_soon));
  Py_XSETREF(self->unattributed, Py_NewRef(unattributed));
  return 0;
}

static int HandleMeter_traverse(HandleMeterObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->owner);
  Py_VISIT(self->executor);
  Py_VISIT(self->task_type);
  Py_VISIT(self->call_soon);
  Py_VISIT(self->unattributed);
  return 0;
}

static int HandleMeter_clear(HandleMeterObject * self)
{
  Py_CLEAR(self->owner);
  Py_CLEAR(self->executor);
  Py_CLEAR(self->task_type);
  Py_CLEAR(self->call_soon);
  Py_CLEAR(self->unattributed);
  return 0;
}

/* A Python subclass's instance (the loop) comes here through its own dealloc, which then lets
 * go of its type itself. */
static void HandleMeter_dealloc(HandleMeterObject * self)
{
  PyObject_GC_UnTrack(self);
  HandleMeter_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Whether callback is a step or wake-up of a task: its __self__ is one (as getattr(callback,
 * "__self__", None) says; bound methods and builtin methods without a lookup). -1: error. */
static int steps_a_task(HandleMeterObject * self, PyObject * callback)
{
  PyObject * bound;
  int is_task;
  if (PyMethod_Check(callback)) {
    return PyObject_TypeCheck(PyMethod_GET_SELF(callback), (PyTypeObject *)self->task_type);
  }
  if (PyCFunction_Check(callback)) {
    bound = PyCFunction_GET_SELF(callback);
    return bound != NULL && PyObject_TypeCheck(bound, (PyTypeObject *)self->task_type);
  }
  bound = PyObject_GetAttrString(callback, "__self__");
  if (bound == NULL) {
    if (!PyErr_ExceptionMatches(PyExc_AttributeError)) {
      return -1;
    }
    PyErr_Clear();
    return 0;
  }
  is_task = PyObject_TypeCheck(bound, (PyTypeObject *)self->task_type);
  Py_DECREF(bound);
  return is_task;
}

/* The owner the context names (a new reference; None: nobody), or NULL on error. */
static PyObject * owner_in(HandleMeterObject * self, PyObject * context)
{
  PyObject * owner;
  if (context == NULL || context == Py_None) {
    if (PyContextVar_Get(self->owner, Py_None, &owner) < 0) {
      return NULL;
    }
    return owner;
  }
  if (!PyContext_CheckExact(context)) {
    return Py_NewRef(Py_None);
  }
  owner = PyObject_GetItem(context, self->owner);
  if (owner == NULL && PyErr_ExceptionMatches(PyExc_KeyError)) {
    PyErr_Clear();
    return Py_NewRef(Py_None);
  }
  return owner;
}

/* The loop's own call_soon, called with self and the arguments in stack (nargs, then kwnames'). */
static PyObject * schedule(HandleMeterObject * self, PyObject * const * args, Py_ssize_t nargs, PyObject * kwnames,
                           PyObject * const * before, Py_ssize_t nbefore)
{
  PyObject * local[12];
  PyObject ** stack = local;
  PyObject * result;
  Py_ssize_t nkw = kwnames != NULL ? PyTuple_GET_SIZE(kwnames) : 0;
  Py_ssize_t total = 1 + nbefore + nargs + nkw, i;
  if (total > (Py_ssize_t)(sizeof(local) / sizeof(local[0]))) {
    stack = PyMem_Malloc((size_t)total * sizeof(PyObject *));
    if (stack == NULL) {
      return PyErr_NoMemory();
    }
  }
  stack[0] = (PyObject *)self;
  for (i = 0; i < nbefore; ++i) {
    stack[1 + i] = before[i];
  }
  for (i = 0; i < nargs + nkw; ++i) {
    stack[1 + nbefore + i] = args[i];
  }
  result = PyObject_Vectorcall(self->call_soon, stack, (size_t)(1 + nbefore + nargs), kwnames);
  if (stack != local) {
    PyMem_Free(stack);
  }
  return result;
}

/* call_soon(callback, *args, context=None) -> Handle */
static PyObject * HandleMeter_call_soon(HandleMeterObject * self, PyObject * const * args, Py_ssize_t nargs,
                                        PyObject * kwnames)
{
  PyObject * context = NULL, * owner, * account = NULL, * call = NULL, * arrived = NULL, * result = NULL;
  PyObject * before[2];
  Py_ssize_t i, nkw = kwnames != NULL ? PyTuple_GET_SIZE(kwnames) : 0;
  int is_task;
  if (self->call_soon == NULL) {
    PyErr_SetString(PyExc_TypeError, "HandleMeter.__init__ was not called");
    return NULL;
  }
  if (nargs < 1) {
    return schedule(self, args, nargs, kwnames, NULL, 0); /* the loop's own call_soon says what is missing */
  }
  for (i = 0; i < nkw; ++i) {
    if (PyUnicode_CompareWithASCIIString(PyTuple_GET_ITEM(kwnames, i), "context") == 0) {
      context = args[nargs + i];
    }
  }
  owner = owner_in(self, context);
  if (owner == NULL) {
    return NULL;
  }
  if (owner == self->executor) {
    Py_DECREF(owner);
    return schedule(self, args, nargs, kwnames, NULL, 0);
  }
  is_task = steps_a_task(self, args[0]);
  if (is_task != 0) {
    Py_DECREF(owner);
    return is_task < 0 ? NULL : schedule(self, args, nargs, kwnames, NULL, 0);
  }
  account = PyObject_CallMethod(owner == Py_None ? self->unattributed : owner, "account", "s", "loop_callback");
  if (account == NULL) {
    goto done;
  }
  call = PyObject_GetAttrString(account, "call");
  if (call == NULL) {
    goto done;
  }
  arrived = PyLong_FromLongLong(monotonic_ns());
  if (arrived == NULL) {
    goto done;
  }
  before[0] = call;
  before[1] = arrived;
  result = schedule(self, args, nargs, kwnames, before, 2);
done:
  Py_DECREF(owner);
  Py_XDECREF(account);
  Py_XDECREF(call);
  Py_XDECREF(arrived);
  return result;
}

static PyMethodDef HandleMeter_methods[] = {
  {"call_soon", (PyCFunction)(void (*)(void))HandleMeter_call_soon, METH_FASTCALL | METH_KEYWORDS,
   "call_soon(callback, *args, context=None) -> Handle: the loop's own, a node's handle metered as its "
   "(see container/executor/_loop.py)"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject HandleMeterType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.HandleMeter",
  .tp_doc = "HandleMeter(owner, executor, task_type, call_soon, unattributed): the first base of an event loop "
            "whose call_soon meters each handle a node's code schedules as that node's.",
  .tp_basicsize = sizeof(HandleMeterObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE | Py_TPFLAGS_HAVE_GC,
  /* tp_new: object's, set by the module (handle_meter_ready): it gives a Python subclass's
   * instance (the loop) its dictionary's inline values, as a plain Python class's instance has;
   * PyType_GenericNew does not, and every attribute the loop's own Python code reads (about a
   * hundred a round trip of a byte over asyncio streams) went the slow way: 4-8% of it. */
  .tp_init = (initproc)HandleMeter_init,
  .tp_dealloc = (destructor)HandleMeter_dealloc,
  .tp_traverse = (traverseproc)HandleMeter_traverse,
  .tp_clear = (inquiry)HandleMeter_clear,
  .tp_methods = HandleMeter_methods,
};

int handle_meter_ready(void)
{
  HandleMeterType.tp_new = PyBaseObject_Type.tp_new;
  return PyType_Ready(&HandleMeterType);
}
