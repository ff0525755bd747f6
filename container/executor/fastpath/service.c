/* Server and Caller: a service's requests and answers, and a client's
 * responses, taken and sent in C (see module.c). */
#include "fastpath.h"

/* Whether rcl_send_response's failure means the client's response reader is
 * not matched (yet): rmw waited for it, up to the writer's blocking time
 * (Fast DDS: 100 ms), and gave up. rcl (since 2023, ros2/rcl#1048: Jazzy,
 * Kilted) passes rmw_fastrtps's RMW_RET_TIMEOUT on as RCL_RET_TIMEOUT;
 * tests/executor/test_fastpath.py checks it on each distribution. */
static inline int client_not_matched(rcl_ret_t ret)
{
  return ret == RCL_RET_TIMEOUT;
}

/* ------------------------------------------------------------------------ */
/* Server: one service's requests, taken into a kept C message, and its answers. */
typedef struct {
  PyObject_HEAD
  Held service;                 /* rcl_service_t */
  MessageFunctions request;     /* of srv_type.Request */
  MessageFunctions response;    /* of srv_type.Response, with from_py */
  void * kept;                  /* owned: the kept request, made with request.create */
} ServerObject;

static int Server_init(ServerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"service", "srv_type", NULL};
  PyObject * service, * srv_type;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "$OO", keywords, &service, &srv_type)) {
    return -1;
  }
  if (self->kept != NULL || self->service.handle != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Server is initialised once");
    return -1;
  }
  if (message_functions(srv_type, "Request", 0, &self->request) < 0) {
    return -1;
  }
  if (message_functions(srv_type, "Response", 1, &self->response) < 0 || held_enter(&self->service, service) < 0) {
    message_functions_clear(&self->request);
    message_functions_clear(&self->response);
    return -1;
  }
  if ((self->kept = self->request.create()) == NULL) {
    held_exit(&self->service);
    message_functions_clear(&self->request);
    message_functions_clear(&self->response);
    PyErr_NoMemory();
    return -1;
  }
  return 0;
}

static void server_close(ServerObject * self)
{
  if (self->kept != NULL) {
    self->request.destroy(self->kept);
    self->kept = NULL;
  }
  held_exit(&self->service);
}

static void Server_dealloc(ServerObject * self)
{
  server_close(self);
  message_functions_clear(&self->request);
  message_functions_clear(&self->response);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * Server_close(ServerObject * self, PyObject * Py_UNUSED(ignored))
{
  server_close(self);
  Py_RETURN_NONE;
}

static PyObject * Server_get_closed(ServerObject * self, void * Py_UNUSED(closure))
{
  return PyBool_FromLong(self->kept == NULL);
}

static int server_open(ServerObject * self)
{
  if (self->kept == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Server not initialised, or closed");
    return 0;
  }
  return 1;
}

/* take() -> (request, header) | None; the header is opaque (bytes), for send(). */
static PyObject * Server_take(ServerObject * self, PyObject * Py_UNUSED(ignored))
{
  rmw_service_info_t info;
  rcl_ret_t ret;
  PyObject * request, * header;
  if (!server_open(self)) {
    return NULL;
  }
  ret = rcl_take_request_with_info(self->service.pointer, &info, self->kept);
  if (ret == RCL_RET_SERVICE_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_take_request_with_info");
  }
  if ((request = self->request.to_py(self->kept)) == NULL) {
    return NULL;
  }
  header = PyBytes_FromStringAndSize((const char *)&info.request_id, sizeof(info.request_id));
  if (header == NULL) {
    Py_DECREF(request);
    return NULL;
  }
  return Py_BuildValue("(NN)", request, header);
}

/* send(response, header, let_go=False) -> bool: False when the client's
 * response reader is not matched (yet): rmw timed out waiting for it, up to
 * 100 ms. With let_go, the GIL is let go meanwhile (a thread that retries
 * such answers; the dispatching threads keep it, as rclpy does: a send that
 * lets go may wait for the GIL behind a busy thread). A response of another
 * type is a TypeError, as in rclpy. */
static PyObject * Server_send(ServerObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  rmw_request_id_t header;
  char * bytes;
  Py_ssize_t size;
  void * message;
  rcl_ret_t ret;
  int is_response, let_go = 0;
  if (nargs < 2 || nargs > 3 || !PyBytes_Check(args[1])) {
    PyErr_SetString(PyExc_TypeError, "send(response, header, let_go=False), the header from take()");
    return NULL;
  }
  if (nargs == 3 && (let_go = PyObject_IsTrue(args[2])) < 0) {
    return NULL;
  }
  if (!server_open(self)) {
    return NULL;
  }
  if (PyBytes_AsStringAndSize(args[1], &bytes, &size) < 0) {
    return NULL;
  }
  if (size != (Py_ssize_t)sizeof(header)) {
    PyErr_SetString(PyExc_ValueError, "not a header from take()");
    return NULL;
  }
  memcpy(&header, bytes, sizeof(header));
  if ((is_response = PyObject_IsInstance(args[0], self->response.type)) <= 0) {
    if (is_response == 0) {
      PyErr_Format(
        PyExc_TypeError, "a service callback returned %.200s, not %.200s", Py_TYPE(args[0])->tp_name,
        ((PyTypeObject *)self->response.type)->tp_name);
    }
    return NULL;
  }
  if ((message = self->response.create()) == NULL) {
    return PyErr_NoMemory();
  }
  if (!self->response.from_py(args[0], message)) {
    self->response.destroy(message);
    if (!PyErr_Occurred()) {
      PyErr_SetString(PyExc_ValueError, "the response could not be converted");
    }
    return NULL;
  }
  if (let_go) {
    /* Entered once more for the send: a close() meanwhile (another thread
     * holds the GIL then) cannot let the service be destroyed under it. */
    Held sending;
    if (held_enter(&sending, self->service.handle) < 0) {
      self->response.destroy(message);
      return NULL;
    }
    Py_BEGIN_ALLOW_THREADS
    ret = rcl_send_response(sending.pointer, &header, message);
    Py_END_ALLOW_THREADS
    held_exit(&sending);
  } else {
    ret = rcl_send_response(self->service.pointer, &header, message);
  }
  self->response.destroy(message);
  if (ret == RCL_RET_OK) {
    Py_RETURN_TRUE;
  }
  if (client_not_matched(ret)) {
    rcl_reset_error();
    Py_RETURN_FALSE;
  }
  return rcl_failed("rcl_send_response");
}

static PyMethodDef Server_methods[] = {
  {"take", (PyCFunction)Server_take, METH_NOARGS, "take() -> (request, header) | None"},
  {"send", (PyCFunction)(void (*)(void))Server_send, METH_FASTCALL,
   "send(response, header, let_go=False) -> bool: False while the client's response reader is not matched"},
  {"close", (PyCFunction)Server_close, METH_NOARGS, "close() -> None: let the service's handle go"},
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Server_getset[] = {
  {"closed", (getter)Server_get_closed, NULL, "Whether close() let the handle go (rclpy's calls serve it then).", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject ServerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Server",
  .tp_doc = "One rcl service's requests taken into a kept C message, and its answers sent.",
  .tp_basicsize = sizeof(ServerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Server_init,
  .tp_dealloc = (destructor)Server_dealloc,
  .tp_methods = Server_methods,
  .tp_getset = Server_getset,
};

/* ------------------------------------------------------------------------ */
/* Caller: one client's responses, taken into a kept C message. */
typedef struct {
  PyObject_HEAD
  Held client;                /* rcl_client_t */
  MessageFunctions response;  /* of srv_type.Response */
  void * kept;                /* owned: the kept response, made with response.create */
} CallerObject;

static int Caller_init(CallerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"client", "srv_type", NULL};
  PyObject * client, * srv_type;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "$OO", keywords, &client, &srv_type)) {
    return -1;
  }
  if (self->kept != NULL || self->client.handle != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Caller is initialised once");
    return -1;
  }
  if (message_functions(srv_type, "Response", 0, &self->response) < 0) {
    return -1;
  }
  if (held_enter(&self->client, client) < 0) {
    message_functions_clear(&self->response);
    return -1;
  }
  if ((self->kept = self->response.create()) == NULL) {
    held_exit(&self->client);
    message_functions_clear(&self->response);
    PyErr_NoMemory();
    return -1;
  }
  return 0;
}

static void caller_close(CallerObject * self)
{
  if (self->kept != NULL) {
    self->response.destroy(self->kept);
    self->kept = NULL;
  }
  held_exit(&self->client);
}

static void Caller_dealloc(CallerObject * self)
{
  caller_close(self);
  message_functions_clear(&self->response);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * Caller_close(CallerObject * self, PyObject * Py_UNUSED(ignored))
{
  caller_close(self);
  Py_RETURN_NONE;
}

/* take() -> (sequence_number, response) | None */
static PyObject * Caller_take(CallerObject * self, PyObject * Py_UNUSED(ignored))
{
  rmw_service_info_t info;
  rcl_ret_t ret;
  PyObject * response;
  if (self->kept == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Caller not initialised, or closed");
    return NULL;
  }
  ret = rcl_take_response_with_info(self->client.pointer, &info, self->kept);
  if (ret == RCL_RET_CLIENT_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_take_response_with_info");
  }
  if ((response = self->response.to_py(self->kept)) == NULL) {
    return NULL;
  }
  return Py_BuildValue("(LN)", (long long)info.request_id.sequence_number, response);
}

static PyMethodDef Caller_methods[] = {
  {"take", (PyCFunction)Caller_take, METH_NOARGS, "take() -> (sequence_number, response) | None"},
  {"close", (PyCFunction)Caller_close, METH_NOARGS, "close() -> None: let the client's handle go"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject CallerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Caller",
  .tp_doc = "One rcl client's responses taken into a kept C message.",
  .tp_basicsize = sizeof(CallerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Caller_init,
  .tp_dealloc = (destructor)Caller_dealloc,
  .tp_methods = Caller_methods,
};
